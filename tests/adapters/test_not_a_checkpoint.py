"""A file prop reads in another role (data, inputs, an ONNX graph, a key), given as the checkpoint, is
named for what it is and where it goes, not called a corrupt torch file (issue 41)."""

from __future__ import annotations

import numpy as np
import pytest

from prop_adapters import load_checkpoint
from prop_cli.errors import PropError
from tests.conftest import make_mlp_checkpoint


def _files(tmp_path):
    x = np.zeros((8, 4), np.float32)
    np.savez(tmp_path / "mine.npz", x=x, y=x[:, :2])
    (tmp_path / "mine.npz").rename(tmp_path / "renamed.bin")  # the zip's members say it, not the name
    np.savez(tmp_path / "mine.npz", x=x, y=x[:, :2])
    np.save(tmp_path / "x.npy", x)
    (tmp_path / "m.onnx").write_bytes(b"\x08\x07\x12\x07pytorch")
    (tmp_path / "k.bin").write_bytes(bytes(range(16)))
    return tmp_path


@pytest.mark.parametrize(
    "name, what, goes",
    [
        ("mine.npz", "is a data file (.npz)", "the data goes in --data"),
        ("renamed.bin", "is a data file (.npz)", "the data goes in --data"),
        ("x.npy", "is an array file (.npy)", "arrays go in prop run --input"),
        ("m.onnx", "is an ONNX graph (.onnx)", "exported from"),
        ("k.bin", "is a key file (16 bytes", "keys go in --key-file"),
    ],
)
def test_a_file_of_another_role_is_named(tmp_path, name, what, goes):
    _files(tmp_path)
    with pytest.raises(PropError) as e:
        load_checkpoint(tmp_path / name)
    text = str(e.value)
    assert what in text and goes in text and "not a model's weights" in text, text
    assert "corrupt" not in text and "torch file" not in text


def test_personalize_with_the_data_as_checkpoint_says_so_in_one_line(tmp_path, cli, monkeypatch):
    _files(tmp_path)
    (tmp_path / "key").write_bytes(bytes(range(16)))
    (tmp_path / "key").chmod(0o600)
    monkeypatch.chdir(tmp_path)
    r = cli("personalize", "mine.npz", "--data", "mine.npz", "--key-file", "key", "--out", "b")
    assert r.code == 2 and len(r.err.strip().splitlines()) == 1, r.err
    assert "mine.npz is a data file (.npz)" in r.err and "--data" in r.err
    assert not (tmp_path / "b").exists()


def test_real_checkpoints_still_read(tmp_path):
    """The recognition never takes a checkpoint for something else: safetensors and torch zips (a
    zip archive too) load."""
    import torch

    make_mlp_checkpoint(tmp_path / "m.safetensors")
    model = load_checkpoint(tmp_path / "m.safetensors")
    torch.save(model.module.state_dict(), tmp_path / "m.pt")
    torch.save(model.module.state_dict(), tmp_path / "m.bin")
    for name in ("m.pt", "m.bin"):
        assert load_checkpoint(tmp_path / name).module is not None
