"""Key material: key files, passphrase-derived keys, which key goes with which bundle, ±1 codes.

Bit order everywhere: for each byte, most significant bit first (``np.unpackbits``). Nothing
here logs, prints or puts key bits into an error message.
"""

from __future__ import annotations

import hashlib
import os
import stat
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from prop_cli import constants as C
from prop_cli.constants import (
    ENV_PASSPHRASE,
    KEY_BITS_MAX,
    KEY_BITS_MIN,
    SALT_BYTES,
    SCRYPT_N,
    SCRYPT_P,
    SCRYPT_R,
)
from prop_cli.errors import PropError, plural
from prop_cli.files import KEY, check_replaceable, check_writable, uninterrupted, wrote

# scrypt needs 128*r*N*p bytes (16 MiB with the defaults); OpenSSL's own cap is 32 MiB, so give
# it explicit headroom instead of relying on that default.
_SCRYPT_MAXMEM = 4 * 128 * SCRYPT_R * SCRYPT_N * SCRYPT_P


class PropKeyWarning(UserWarning):
    """A key file others can read (like ssh's 'UNPROTECTED PRIVATE KEY FILE')."""


def check_bits(bits: int, flag: str = "--bits") -> int:
    """Validate a key size: a multiple of 8 in [KEY_BITS_MIN, KEY_BITS_MAX]."""
    if (
        isinstance(bits, bool)
        or not isinstance(bits, int)
        or bits % 8
        or not (KEY_BITS_MIN <= bits <= KEY_BITS_MAX)
    ):
        raise PropError(
            f"{flag} {bits} is not a valid key size",
            f"use a multiple of 8 between {KEY_BITS_MIN} and {KEY_BITS_MAX} (default 128)",
        )
    return bits


def generate_key_file(path: Path, bits: int = 128, force: bool = False) -> None:
    """Write ``bits/8`` random bytes to ``path`` with mode 0600; never overwrite without force."""
    check_bits(bits)
    path = Path(path)
    # --force replaces a key file only (files.KEY: a file of a key's size), never a folder or another file.
    if check_replaceable(path, KEY, "PATH") and not force:
        raise PropError(
            f"key file {path} already exists",
            "choose another path, or pass --force to replace it (the old key is then lost)",
        )
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise PropError(f"directory {parent} for key file {path} does not exist", "create it first")
    check_writable(parent, "key file", "PATH", path, as_folder=False)
    data = os.urandom(bits // 8)
    if not force:
        # O_EXCL: even a file appearing since the check above is never clobbered.
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        except FileExistsError:
            raise PropError(
                f"key file {path} already exists", "choose another path, or pass --force"
            ) from None
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
        except BaseException:
            path.unlink(missing_ok=True)
            raise
    else:
        # mkstemp creates 0600; os.replace makes the swap atomic, so no half-written key.
        fd, tmp = tempfile.mkstemp(dir=parent, prefix=f".{path.name}.", suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
            with uninterrupted():
                os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    os.chmod(path, 0o600)  # the umask can only remove bits, but be explicit
    wrote(path)


def read_key_file(path: Path, bits: int | None = None) -> np.ndarray:
    """Key bits (uint8 0/1, length 8*size) from a key file; ``bits`` is what a bundle expects."""
    path = Path(path)
    if not path.exists():
        raise PropError(
            f"key file {path} does not exist", "check the --key-file path, or create a key with prop keygen"
        )
    if path.is_dir():
        raise PropError(f"key file {path} is a directory", "pass the key file itself to --key-file")
    st = path.stat()
    size = st.st_size
    if size == 0:
        raise PropError(f"key file {path} is empty", "pass the key file written by prop keygen")
    if bits is not None and size * 8 != bits:
        raise PropError(
            f"key file {path} has {plural(size, 'byte')} but the bundle expects {bits} bits = "
            f"{bits // 8} bytes",
            "use the key the bundle was personalized with",
        )
    if bits is None and not (KEY_BITS_MIN // 8 <= size <= KEY_BITS_MAX // 8):
        raise PropError(
            f"key file {path} has {plural(size, 'byte')}; key files hold {KEY_BITS_MIN // 8} to "
            f"{KEY_BITS_MAX // 8} bytes",
            "check that --key-file points at a key written by prop keygen",
        )
    if os.name == "posix" and stat.S_IMODE(st.st_mode) & 0o077:
        warnings.warn(
            f"key file {path} is readable by other users (mode {stat.S_IMODE(st.st_mode):o}); "
            f"run: chmod 600 {path}",
            PropKeyWarning,
            stacklevel=2,
        )
    try:
        data = path.read_bytes()
    except OSError as e:
        raise PropError(f"key file {path} cannot be read ({e.strerror})", "check its permissions") from None
    return np.unpackbits(np.frombuffer(data, dtype=np.uint8))


@dataclass
class KeySource:
    """One user's key and how it was given; ``bits`` never leaves memory."""

    bits: np.ndarray  # 0/1, uint8
    kind: str  # "file" | "passphrase"


def new_salt() -> bytes:
    """Fresh random salt for a passphrase key (stored in the bundle manifest; not secret)."""
    return os.urandom(SALT_BYTES)


def passphrase_bits(passphrase: str, salt: bytes, bits: int) -> np.ndarray:
    """Key bits derived from a passphrase with scrypt (memory-hard, so guessing is slow)."""
    if not passphrase:
        raise PropError(
            "the passphrase is empty",
            f"pass a non-empty --passphrase or set {ENV_PASSPHRASE}",
        )
    if bits <= 0 or bits % 8:
        raise PropError(f"key size {bits} bits is not a positive multiple of 8", "use e.g. 128")
    if not salt:
        raise PropError("the passphrase salt is empty", "the bundle manifest is damaged")
    key = hashlib.scrypt(
        passphrase.encode("utf-8"),
        salt=bytes(salt),
        n=SCRYPT_N,
        r=SCRYPT_R,
        p=SCRYPT_P,
        maxmem=_SCRYPT_MAXMEM,
        dklen=bits // 8,
    )
    return np.unpackbits(np.frombuffer(key, dtype=np.uint8))


def to_signs(bits: np.ndarray | torch.Tensor) -> torch.Tensor:
    """0/1 bits of shape (n,) or (K, n) -> float32 ±1 (bit 1 -> +1, bit 0 -> -1)."""
    t = torch.as_tensor(np.asarray(bits) if not torch.is_tensor(bits) else bits)
    if t.ndim not in (1, 2):
        raise ValueError(f"key bits must have shape (n,) or (K, n), got {tuple(t.shape)}")
    return t.to(torch.float32) * 2.0 - 1.0


def hamming_distance(a: np.ndarray | torch.Tensor, b: np.ndarray | torch.Tensor) -> int:
    """Number of positions where two equal-length bit vectors differ."""
    a_np = a.detach().cpu().numpy() if torch.is_tensor(a) else np.asarray(a)
    b_np = b.detach().cpu().numpy() if torch.is_tensor(b) else np.asarray(b)
    if a_np.shape != b_np.shape:
        raise ValueError(f"cannot compare keys of shapes {a_np.shape} and {b_np.shape}")
    return int(np.count_nonzero(a_np != b_np))


def user_keys(
    key_files: list[Path], passphrases: list[str], bits: int = C.KEY_BITS_DEFAULT, *, allow_weak: bool = False
) -> tuple[list[KeySource], bytes | None]:
    """Keys for `personalize`: key files first, then passphrases (one fresh salt per bundle, shared
    by its passphrase users, stored in the manifest); returns the keys and that salt (None if none).
    A passphrase that takes less than PASSPHRASE_MIN_YEARS to guess is refused unless ``allow_weak``."""
    from .passphrase import check_strength

    keys = [KeySource(read_key_file(p), "file") for p in key_files]
    for i, phrase in enumerate(passphrases):
        check_strength(phrase, f"the passphrase of user {len(key_files) + i + 1}", allow_weak)
    salt = None
    if passphrases:
        check_bits(bits)
        salt = new_salt()
        keys += [KeySource(passphrase_bits(p, salt, bits), "passphrase") for p in passphrases]
    return keys, salt


def kdf_record(salt: bytes | None) -> dict | None:
    """What the manifest keeps to derive a passphrase key again (the salt is not secret)."""
    if salt is None:
        return None
    return {"name": "scrypt", "n": SCRYPT_N, "r": SCRYPT_R, "p": SCRYPT_P, "salt": salt.hex()}


def key_for_bundle(
    manifest: dict, key_file: Path | None = None, passphrase: str | None = None
) -> np.ndarray | None:
    """The key bits for an existing bundle, from a key file or its passphrase (salt in the manifest)."""
    bits = int(manifest[C.M_KEY]["bits"])
    if key_file is not None and passphrase is not None:
        raise PropError("--key-file and --passphrase both given", "use one of them")
    if key_file is not None:
        return read_key_file(key_file, bits)
    if passphrase is not None:
        kdf = manifest[C.M_KEY].get("kdf")
        if not kdf:
            raise PropError("this bundle was not made with a passphrase", "use --key-file")
        return passphrase_bits(passphrase, bytes.fromhex(kdf["salt"]), bits)
    return None


def key_text(path: Path) -> str:
    """A key file as text, for a header (``prop serve``'s ``Authorization: Api-Key <text>``): the hex of
    its bytes, read and checked as ``read_key_file`` reads them."""
    return np.packbits(read_key_file(path)).tobytes().hex()


def key_from_text(text: str, bits: int) -> np.ndarray:
    """``key_text``'s text back to key bits for a bundle of ``bits``-bit keys. A refusal never quotes the
    text (it is the key)."""
    text = text.strip()
    if len(text) != bits // 4:
        raise PropError(
            f"the key text has {len(text)} characters; this bundle's keys are {bits // 4} hex characters",
            "send the key file's bytes in hex (prop_cli.core.key_files.key_text)",
        )
    try:
        data = bytes.fromhex(text)
    except ValueError:
        raise PropError("the key text is not hex", "send the key file's bytes in hex (key_text)") from None
    return np.unpackbits(np.frombuffer(data, dtype=np.uint8))
