"""Sealed records: one user's part of a bundle, encrypted under a key derived from their key.

The cipher is AES-256-GCM (authenticated) and the cipher key is HKDF-SHA256 of the user's key bytes
with a random salt of the record's own; both come from ``cryptography``. A passphrase user's key
bytes come from scrypt first (keys.passphrase_bits), so the passphrase is stretched once and each
record's key is derived from the result.

A record keeps in the clear only a random id (not derived from the key), its HKDF salt and its GCM
nonce, and since format 6 its lookup name (``lookup_name``: a keyed hash of the key under the bundle
id, what a key finds its record by, ``lookup``). Nothing there tests a key faster than one HKDF, which
attempting the decryption costs anyway. The associated data binds a record to the public part
of its bundle (``records.binding``): edit the manifest's model, layers or base weights and every
record fails to open.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from prop_cli.errors import PropError

# Domain separation: changing it changes the meaning of every sealed bundle. Enrolments (``enrol``)
# derive their AES keys under ENROL_INFO, so the same key bits give unrelated AES keys for each use.
SEAL_INFO = b"prop/seal/v1"
ENROL_INFO = b"prop/enrol/v1"
# Format 6: a record's or enrolment's lookup name (``lookup``), HKDF of the key bytes under this label and
# the bundle id as salt: unrelated to every AES key above (other label, other salt).
LOOKUP_INFO = b"prop/lookup/v1"
LOOKUP_BYTES = 16
BUCKET = 4096  # sealed plaintexts are padded to a multiple of this: sizes say nothing of their metadata
SALT_BYTES = 16
NONCE_BYTES = 12  # GCM's standard nonce size
ID_BYTES = 8
CRYPTO_EXTRA = "pip install cryptography (prop-keys depends on it; reinstall prop-keys)"


def _aead():
    try:
        from cryptography.exceptions import InvalidTag
        from cryptography.hazmat.primitives import hashes
        from cryptography.hazmat.primitives.ciphers.aead import AESGCM
        from cryptography.hazmat.primitives.kdf.hkdf import HKDF
    except ImportError as e:  # a broken install; prop-keys requires cryptography
        raise PropError(
            f"sealed bundles need the 'cryptography' package ({e.name} is missing)", CRYPTO_EXTRA
        ) from None
    return AESGCM, HKDF, hashes, InvalidTag


@dataclass(frozen=True)
class SealedRecord:
    """One user's encrypted payload and the public values needed to open it with their key."""

    id: str  # random hex, only to name the record (e.g. for remove-user)
    salt: bytes
    nonce: bytes
    ciphertext: bytes | None  # AES-GCM output: ciphertext + 16-byte tag (None: in its file, read when tried)
    lookup: str | None = None  # format 6: the name the record is filed under (``lookup_name``)


def key_bytes(bits: np.ndarray) -> bytes:
    """Key bits (0/1, most significant bit first) -> the bytes of the key file they came from."""
    bits = np.asarray(bits, dtype=np.uint8)
    if bits.ndim != 1 or len(bits) % 8:
        raise ValueError(f"key bits must be a flat multiple of 8, got shape {bits.shape}")
    return np.packbits(bits).tobytes()


def lookup_name(bits: np.ndarray, bundle_id: str) -> str:
    """The name a key's record or enrolment is filed under in the bundle ``bundle_id`` (hex): HKDF-SHA256
    of the key bytes, salted with the bundle id, under ``LOOKUP_INFO``; 16 bytes, hex. A pseudo-random
    function of the key: without it the name says nothing of it (``lookup``)."""
    _, hkdf, hashes, _ = _aead()
    kdf = hkdf(
        algorithm=hashes.SHA256(), length=LOOKUP_BYTES, salt=bytes.fromhex(bundle_id), info=LOOKUP_INFO
    )
    return kdf.derive(key_bytes(bits)).hex()


def _cipher(bits: np.ndarray, salt: bytes, info: bytes = SEAL_INFO):
    aesgcm, hkdf, hashes, _ = _aead()
    key = hkdf(algorithm=hashes.SHA256(), length=32, salt=salt, info=info).derive(key_bytes(bits))
    return aesgcm(key)


def encrypt(plaintext: bytes, bits: np.ndarray, associated: bytes, info: bytes) -> tuple[bytes, bytes, bytes]:
    """(salt, nonce, ciphertext) of ``plaintext`` under HKDF(key bytes, a fresh salt, ``info``)."""
    salt, nonce = os.urandom(SALT_BYTES), os.urandom(NONCE_BYTES)
    # A fresh salt gives a fresh AES key, so a (key, nonce) pair is never used twice.
    return salt, nonce, _cipher(bits, salt, info).encrypt(nonce, plaintext, associated)


def decrypt(
    salt: bytes, nonce: bytes, ciphertext: bytes, bits: np.ndarray, associated: bytes, info: bytes
) -> bytes | None:
    """The plaintext if ``bits`` is the key it was encrypted for (and nothing was tampered with)."""
    *_, invalid_tag = _aead()
    try:
        return _cipher(bits, salt, info).decrypt(nonce, ciphertext, associated)
    except invalid_tag:
        return None


def seal(
    payload: bytes, bits: np.ndarray, associated: Callable[[str], bytes], bundle_id: str | None = None
) -> SealedRecord:
    """Encrypt ``payload`` for the key ``bits``; ``associated(record_id)`` gives the bound data.
    ``bundle_id`` (format 6): the record is filed under the key's lookup name in that bundle."""
    record_id = os.urandom(ID_BYTES).hex()
    salt, nonce, ct = encrypt(payload, bits, associated(record_id), SEAL_INFO)
    lookup = None if bundle_id is None else lookup_name(bits, bundle_id)
    return SealedRecord(record_id, salt, nonce, ct, lookup)


def open_record(
    record: SealedRecord, bits: np.ndarray, associated: bytes, ciphertext: bytes | None = None
) -> bytes | None:
    """The payload if ``bits`` is the record's key (and nothing was tampered with), else None.
    ``ciphertext``: the record's, where it was read from its file (``record.ciphertext`` is None)."""
    data = record.ciphertext if ciphertext is None else ciphertext
    return decrypt(record.salt, record.nonce, data, bits, associated, SEAL_INFO)


def pad(body: bytes, bucket: int = BUCKET) -> bytes:
    """``body`` framed by its length and padded with zeros to a multiple of ``bucket`` bytes, so that
    ciphertext sizes fall in fixed buckets whatever the metadata inside."""
    framed = len(body).to_bytes(8, "little") + body
    return framed + bytes(-len(framed) % bucket)


def unpad(data: bytes) -> bytes:
    """Inverse of ``pad``; only called on authenticated plaintext."""
    n = int.from_bytes(data[:8], "little")
    return data[8 : 8 + n]


# --- the plaintext: tensors + a little metadata, as safetensors bytes --------------------------


def encode_payload(tensors: dict[str, torch.Tensor], meta: dict) -> bytes:
    """safetensors bytes; ``meta`` (JSON-serialisable) rides in the header's metadata."""
    from safetensors.torch import save

    flat = {k: v.detach().to("cpu", torch.float32).contiguous() for k, v in tensors.items()}
    return save(flat, metadata={"prop": json.dumps(meta, sort_keys=True)})


def decode_payload(data: bytes) -> tuple[dict[str, torch.Tensor], dict]:
    """Inverse of encode_payload; only called on authenticated plaintext."""
    from safetensors.torch import load

    # safetensors layout: 8-byte little-endian header length, then the JSON header.
    n = int.from_bytes(data[:8], "little")
    header = json.loads(data[8 : 8 + n])
    meta = json.loads((header.get("__metadata__") or {}).get("prop", "{}"))
    return load(data), meta
