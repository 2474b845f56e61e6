"""The records of a sealed bundle: one user's payload each, encrypted under a key derived from their key.

A sealed bundle's base is the original checkpoint; each user's payload (``prop_cli.core.payload``)
is an AES-GCM record (``cipher``) that only their key opens. A record's associated data binds it to
the public fields that decide how a payload is applied (``binding``): edit the model, the payload
layout, the task or the base weights and every record fails to open. A wrong key opens nothing.

This module reads, opens, writes and rewrites records; training a payload is ``prop_cli.train``.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from prop_cli import constants as C
from prop_cli.core.payload import Payload, PayloadSpec
from prop_cli.errors import PropError
from prop_cli.files import dump_json, sha256_file, write_text

from .cipher import SealedRecord, decode_payload, encode_payload, open_record, seal
from .manifest import restamp

# The manifest fields that decide how a payload is applied; the cipher authenticates them with every
# record (associated data), so an edit to any of them makes every record fail to open. Metrics,
# config, the audit summary and the records list are informational and may change (add-user, attack
# --record) without re-encrypting anyone's record.
_BOUND = (C.M_FORMAT, C.M_MODE, C.M_MODEL, C.M_PAYLOAD, C.M_TASK)
# What of a sealed user's report the clear manifest keeps: the wrong keys' figures only (their own
# personalization is sealed in their record).
PUBLIC_METRICS = ("samples", "null", "random", "hamming1")


def public_part(manifest: dict) -> dict:
    """The manifest fields that opening a record needs (an ONNX export carries them)."""
    part = {f: manifest.get(f) for f in _BOUND}
    part.update({C.M_IO: manifest[C.M_IO], C.M_KEY: manifest[C.M_KEY], C.M_FILES: manifest[C.M_FILES]})
    part[C.M_RECORDS] = manifest[C.M_RECORDS]
    return part


def binding(manifest: dict, record_id: str) -> bytes:
    """The associated data of one record: a digest of the bundle's bound public fields and its id."""
    key = manifest[C.M_KEY]
    bound = {f: manifest.get(f) for f in _BOUND}
    bound["input_shape"] = manifest[C.M_IO]["input_shape"]
    bound["key"] = {"bits": key["bits"], "kdf": key.get("kdf")}
    bound["base_sha256"] = manifest[C.M_FILES][C.BASE_WEIGHTS]
    bound["record"] = record_id
    text = json.dumps(bound, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(b"prop/seal/binding/v1\0" + text.encode()).digest()


@dataclass
class Opened:
    record_id: str
    payload: Payload
    meta: dict  # what was sealed beside the tensors: the user's metrics and training settings


@dataclass
class SealedState:
    """A sealed bundle's public part beyond the base: the payload layout and the encrypted records."""

    manifest: dict
    spec: PayloadSpec
    records: list[SealedRecord]

    def __post_init__(self) -> None:
        # The associated data of each record, computed once: the audit tries a million keys.
        self._bound = [binding(self.manifest, rec.id) for rec in self.records]

    def open(self, bits: np.ndarray) -> Opened | None:
        """The user's payload if ``bits`` opens one of the records, else None (a wrong key)."""
        for rec, bound in zip(self.records, self._bound):
            data = open_record(rec, bits, bound)
            if data is not None:
                tensors, meta = decode_payload(data)
                return Opened(rec.id, Payload.from_tensors(self.spec, tensors).eval(), meta)
        return None


def record_file(record_id: str) -> str:
    return f"{C.RECORDS_DIR}/{record_id}{C.RECORD_SUFFIX}"


def record_entry(rec: SealedRecord) -> dict:
    """A record's manifest entry: where its file is and what opening it needs besides the key."""
    return {
        "id": rec.id,
        "file": record_file(rec.id),
        "salt": rec.salt.hex(),
        "nonce": rec.nonce.hex(),
        "sha256": hashlib.sha256(rec.ciphertext).hexdigest(),
    }


def _bad(path: Path, what: str) -> PropError:
    return PropError(f"bundle {path}: {what}", "restore the bundle from a trusted copy")


def load_state(path: Path, manifest: dict) -> SealedState:
    """The records of a sealed bundle, each file checked against its sha256 in the manifest."""
    spec = PayloadSpec.from_dict(manifest[C.M_PAYLOAD])
    records = []
    for entry in manifest[C.M_RECORDS]:
        f = path / entry["file"]
        if Path(entry["file"]).parent.name != C.RECORDS_DIR or not f.is_file():
            raise _bad(path, f"user record {entry['file']} is missing")
        if sha256_file(f) != entry["sha256"]:
            raise _bad(
                path, f"{entry['file']} does not match its sha256 in {C.MANIFEST} (modified or corrupt)"
            )
        records.append(
            SealedRecord(
                entry["id"], bytes.fromhex(entry["salt"]), bytes.fromhex(entry["nonce"]), f.read_bytes()
            )
        )
    return SealedState(manifest, spec, records)


def seal_payload(manifest: dict, private: dict, payload: Payload, bits: np.ndarray) -> SealedRecord:
    """Encrypt one user's payload (and ``private``: their metrics and settings, sealed too) for their key."""
    plaintext = encode_payload(payload.tensors(), private)
    return seal(plaintext, bits, lambda rid: binding(manifest, rid))


def write_record(folder: Path, rec: SealedRecord) -> None:
    """Write a record's ciphertext under ``folder``."""
    f = folder / record_file(rec.id)
    f.parent.mkdir(exist_ok=True)
    f.write_bytes(rec.ciphertext)


def with_records(manifest: dict, add: list[SealedRecord], drop: list[str]) -> dict:
    """The manifest with records added and removed (and the removed users' public metrics), not written."""
    new = dict(manifest)
    new[C.M_RECORDS] = [e for e in manifest[C.M_RECORDS] if e["id"] not in drop] + [
        record_entry(rec) for rec in add
    ]
    if new.get(C.M_METRICS):
        users = [u for u in new[C.M_METRICS].get("users", []) if u.get("record") not in drop]
        new[C.M_METRICS] = {**new[C.M_METRICS], "users": users}
    return new


def rewrite_records(bundle: Path, old: dict, new: dict, add: list[SealedRecord]) -> dict:
    """Commit ``new`` (from ``with_records``) to a sealed bundle in place: the added records' files first,
    then the manifest, swapped atomically, then the dropped records' files are deleted. An interruption
    leaves a bundle that loads."""
    for rec in add:
        write_record(bundle, rec)
    new = restamp(new)
    write_text(bundle / C.MANIFEST, dump_json(new), what="manifest", flag="BUNDLE")
    kept = {e["id"] for e in new[C.M_RECORDS]}
    for e in old[C.M_RECORDS]:
        if e["id"] not in kept:
            (bundle / e["file"]).unlink(missing_ok=True)
    return new


def copy_records(src: Path, dst: Path, manifest: dict) -> None:
    """Copy a sealed bundle's record files (for exports: the ONNX runtime opens them too)."""
    (dst / C.RECORDS_DIR).mkdir(parents=True, exist_ok=True)
    for e in manifest[C.M_RECORDS]:
        shutil.copyfile(src / e["file"], dst / e["file"])


def check_new_key(state: SealedState, bits: np.ndarray) -> None:
    if state.open(bits) is not None:
        raise PropError(
            "this key already opens a user of the bundle",
            "use prop remove-user first to replace that user, or give the new user their own key",
        )


def public_metrics(report: dict, record_id: str) -> dict:
    """What of a sealed user's report goes into the manifest (``PUBLIC_METRICS``), by record."""
    return {"record": record_id, **{k: report[k] for k in PUBLIC_METRICS}}
