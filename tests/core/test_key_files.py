"""Key files, passphrase keys, sign encoding."""

from __future__ import annotations

import os
import stat
import warnings

import numpy as np
import pytest
import torch

from prop_cli.core.key_files import (
    PropKeyWarning,
    generate_key_file,
    hamming_distance,
    new_salt,
    passphrase_bits,
    read_key_file,
    to_signs,
)
from prop_cli.errors import PropError

posix_only = pytest.mark.skipif(os.name != "posix", reason="file modes are POSIX")


@posix_only
def test_keygen_mode_and_size(tmp_path):
    path = tmp_path / "user.key"
    generate_key_file(path, bits=256)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert path.stat().st_size == 32
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a fresh key must not trigger the permission warning
        bits = read_key_file(path, bits=256)
    assert bits.dtype == np.uint8 and bits.shape == (256,)
    assert set(np.unique(bits)) <= {0, 1}


def test_keygen_default_is_128_bits(tmp_path):
    generate_key_file(tmp_path / "k")
    assert (tmp_path / "k").stat().st_size == 16


def test_keygen_refuses_overwrite_and_force_replaces(tmp_path):
    path = tmp_path / "user.key"
    generate_key_file(path)
    before = path.read_bytes()
    with pytest.raises(PropError, match=r"user\.key already exists.*--force"):
        generate_key_file(path)
    assert path.read_bytes() == before
    generate_key_file(path, bits=64, force=True)
    assert path.stat().st_size == 8 and path.read_bytes() != before
    if os.name == "posix":
        assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert sorted(p.name for p in tmp_path.iterdir()) == ["user.key"]  # no temp files left


@pytest.mark.parametrize("bits", [0, 24, 100, 1032, 2048, -8])
def test_keygen_bits_validation(tmp_path, bits):
    with pytest.raises(PropError, match=rf"--bits {bits} .*multiple of 8 between 32 and 1024"):
        generate_key_file(tmp_path / "k", bits=bits)
    assert not (tmp_path / "k").exists()


def test_keygen_missing_directory(tmp_path):
    with pytest.raises(PropError, match=r"nodir.* does not exist"):
        generate_key_file(tmp_path / "nodir" / "k")


def test_read_key_bit_order(tmp_path):
    path = tmp_path / "k"
    path.write_bytes(bytes([0b10000001, 0xFF, 0, 0x0F]))
    path.chmod(0o600)
    bits = read_key_file(path)
    assert bits[:8].tolist() == [1, 0, 0, 0, 0, 0, 0, 1]
    assert bits[8:16].tolist() == [1] * 8
    assert bits[24:].tolist() == [0, 0, 0, 0, 1, 1, 1, 1]


def test_read_key_errors(tmp_path):
    with pytest.raises(PropError, match=r"absent\.key does not exist"):
        read_key_file(tmp_path / "absent.key")
    with pytest.raises(PropError, match=r"is a directory"):
        read_key_file(tmp_path)
    (tmp_path / "empty.key").write_bytes(b"")
    with pytest.raises(PropError, match=r"empty\.key is empty"):
        read_key_file(tmp_path / "empty.key")
    generate_key_file(tmp_path / "k64", bits=64)
    with pytest.raises(PropError, match=r"k64 has 8 bytes but the bundle expects 128 bits = 16"):
        read_key_file(tmp_path / "k64", bits=128)
    (tmp_path / "big.key").write_bytes(b"\0" * 4096)
    (tmp_path / "big.key").chmod(0o600)
    with pytest.raises(PropError, match=r"big\.key has 4096 bytes"):
        read_key_file(tmp_path / "big.key")


@posix_only
def test_read_key_permission_warning(tmp_path):
    path = tmp_path / "open.key"
    generate_key_file(path)
    path.chmod(0o644)
    with pytest.warns(PropKeyWarning, match=r"chmod 600 .*open\.key"):
        bits = read_key_file(path)
    assert bits.shape == (128,)


def test_passphrase_deterministic_and_salted():
    salt = b"0123456789abcdef"
    a = passphrase_bits("correct horse", salt, 128)
    assert a.dtype == np.uint8 and a.shape == (128,)
    assert np.array_equal(a, passphrase_bits("correct horse", salt, 128))
    assert not np.array_equal(a, passphrase_bits("correct horse", b"fedcba9876543210", 128))
    assert not np.array_equal(a, passphrase_bits("correct horsf", salt, 128))
    # A longer key extends the shorter one (scrypt output prefix).
    assert np.array_equal(passphrase_bits("correct horse", salt, 256)[:128], a)


def test_passphrase_empty_refused():
    with pytest.raises(PropError, match=r"passphrase is empty.*--passphrase.*PROP_PASSPHRASE"):
        passphrase_bits("", b"salt", 128)


def test_new_salt():
    a, b = new_salt(), new_salt()
    assert len(a) == 16 and a != b


def test_to_signs():
    s = to_signs(np.array([1, 0, 1], dtype=np.uint8))
    assert s.dtype == torch.float32 and s.tolist() == [1.0, -1.0, 1.0]
    batch = to_signs(torch.tensor([[0, 1], [1, 1]]))
    assert batch.shape == (2, 2) and batch.tolist() == [[-1.0, 1.0], [1.0, 1.0]]
    with pytest.raises(ValueError):
        to_signs(np.zeros((2, 2, 2)))


def test_hamming_distance():
    a = np.array([0, 1, 1, 0], dtype=np.uint8)
    b = np.array([1, 1, 0, 0], dtype=np.uint8)
    assert hamming_distance(a, b) == 2
    assert hamming_distance(torch.from_numpy(a), a) == 0
    with pytest.raises(ValueError):
        hamming_distance(a, b[:3])


def test_force_replaces_a_key_file_only(tmp_path):
    """Issue 28: keygen --force replaced any file; it replaces a key file (4..128 bytes, mode 0600)."""
    notes = tmp_path / "notes.txt"
    notes.write_text("my notes\n")
    notes.chmod(0o644)
    if os.name == "posix":  # elsewhere a small file passes for a key: no mode to tell them apart
        with pytest.raises(PropError, match=r"notes\.txt is a file others may read .*not a key file"):
            generate_key_file(notes, force=True)
    (tmp_path / "big").write_bytes(b"\0" * 4096)
    with pytest.raises(PropError, match=r"a file of 4096 bytes, not a key file"):
        generate_key_file(tmp_path / "big", force=True)
    (tmp_path / "sub").mkdir()
    with pytest.raises(PropError, match=r"sub is an empty folder"):
        generate_key_file(tmp_path / "sub", force=True)
    assert notes.read_text() == "my notes\n" and (tmp_path / "big").stat().st_size == 4096
