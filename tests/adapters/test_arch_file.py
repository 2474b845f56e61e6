"""`--arch path/to/file.py:factory`, where a named module must be importable from, and a fully
convolutional model run on another image size than it was personalized on (issue 23)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import save_file

from tests.conftest import FAST, write_keys

CNN = """
from torch import nn


def build():
    return nn.Sequential(nn.Conv2d(1, 4, 3, padding=1), nn.ReLU(), nn.Conv2d(4, 2, 3, padding=1),
                         nn.AdaptiveAvgPool2d(1), nn.Flatten())
"""


def _cnn(d, monkeypatch):
    (d / "models").mkdir()
    (d / "models" / "cnn_file.py").write_text(CNN)
    monkeypatch.syspath_prepend(str(d / "models"))
    import importlib

    torch.manual_seed(0)
    module = importlib.import_module("cnn_file").build()
    save_file({k: v.contiguous() for k, v in module.state_dict().items()}, str(d / "cnn.safetensors"))
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (64, 1, 10, 10)).astype(np.float32)
    np.savez(d / "img.npz", x=x, y=np.stack([x.mean((1, 2, 3)), -x.mean((1, 2, 3))], 1).astype(np.float32))
    write_keys(d, ("k.bin",), rng)
    np.save(d / "x12.npy", rng.uniform(-1, 1, (5, 1, 12, 12)).astype(np.float32))
    np.save(d / "x10.npy", x[:5])


def test_arch_as_a_file_path_and_other_image_sizes(tmp_path, cli, monkeypatch):
    _cnn(tmp_path, monkeypatch)
    monkeypatch.chdir(tmp_path)
    r = cli("personalize", "cnn.safetensors", "--arch", "./models/cnn_file.py:build", "--layers", "2",
            "--data", "img.npz", "--key-file", "k.bin", "--out", "b", *FAST)  # fmt: skip
    assert r.code == 0, r.err
    for name, shape in (("x10", (5, 2)), ("x12", (5, 2))):
        r = cli("run", "b", "--input", f"{name}.npy", "--output", f"{name}-y.npy", "--key-file", "k.bin",
                "--trust-remote-code")  # fmt: skip
        assert r.code == 0, r.err
        assert np.load(tmp_path / f"{name}-y.npy").shape == shape
    # Another folder: the recorded path is relative to where prop runs; the error says so.
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")
    r = cli("run", "../b", "--input", "../x10.npy", "--output", "y.npy", "--trust-remote-code")
    assert r.code == 2 and "relative to the folder prop runs in" in r.err, r.err
    assert len(r.err.strip().splitlines()) == 1 and "TypeError" not in r.err


def test_a_relative_arch_is_given_again_from_another_folder(tmp_path, cli, monkeypatch):
    """Personalized in A with a relative --arch, run from B: the error names the path and --arch, and
    --arch naming the file from B runs the bundle (the user's consent: no --trust-remote-code), the
    user's key included (its enrolment holds: the bundle is unchanged)."""
    a = tmp_path / "A"
    a.mkdir()
    _cnn(a, monkeypatch)
    monkeypatch.chdir(a)
    r = cli("personalize", "cnn.safetensors", "--arch", "models/cnn_file.py:build", "--layers", "2",
            "--data", "img.npz", "--key-file", "k.bin", "--out", "b", *FAST)  # fmt: skip
    assert r.code == 0, r.err
    r = cli("run", "b", "--input", "x10.npy", "--output", "here.npy", "--key-file", "k.bin",
            "--trust-remote-code")  # fmt: skip
    assert r.code == 0, r.err
    (tmp_path / "B").mkdir()
    monkeypatch.chdir(tmp_path / "B")
    run = ["run", "../A/b", "--input", "../A/x10.npy", "--key-file", "../A/k.bin"]
    r = cli(*run, "--output", "y.npy", "--trust-remote-code")
    assert r.code == 2 and "model.arch 'models/cnn_file.py:build'" in r.err and "models/cnn_file.py" in r.err
    assert "pass --arch naming the file's path from here" in r.err and len(r.err.strip().splitlines()) == 1
    r = cli(*run, "--output", "y.npy", "--arch", "../A/models/cnn_file.py:build", "--json")
    assert r.code == 0, r.err
    assert json.loads(r.out)["keyed"] is True
    assert np.array_equal(np.load("y.npy"), np.load(a / "here.npy"))
    # A wrong --arch path names itself, from here; --arch on a bundle not built by one is refused.
    r = cli(*run, "--output", "z.npy", "--arch", "cnn_file.py:build")
    assert r.code == 2 and "--arch 'cnn_file.py:build': cnn_file.py does not exist" in r.err, r.err
    from tests.conftest import write_user_data

    write_user_data(tmp_path / "B", 40, np.random.default_rng(1))
    r = cli("personalize", "model.safetensors", "--data", "mine.npz", "--key-file", "../A/k.bin", "--out",
            "mlp", *FAST)  # fmt: skip
    assert r.code == 0, r.err
    np.save("x4.npy", np.zeros((2, 4), np.float32))
    cnn = "../A/models/cnn_file.py:build"
    r = cli("run", "mlp", "--input", "x4.npy", "--output", "y4.npy", "--arch", cnn)
    assert r.code == 2 and "--arch does not apply to bundle mlp" in r.err and not Path("y4.npy").exists()


def test_a_module_name_says_where_it_must_be_importable_from(tmp_path, cli, monkeypatch):
    _cnn(tmp_path, monkeypatch)
    monkeypatch.chdir(tmp_path)
    r = cli("personalize", "cnn.safetensors", "--arch", "cnn_file:build", "--layers", "2",
            "--data", "img.npz", "--key-file", "k.bin", "--out", "b", *FAST)  # fmt: skip
    assert r.code == 0, r.err
    import sys

    monkeypatch.setattr(sys, "path", [p for p in sys.path if not p.endswith("models")])
    sys.modules.pop("cnn_file", None)
    r = cli("run", "b", "--input", "x10.npy", "--output", "y.npy", "--trust-remote-code")
    assert r.code == 2 and "must be importable from the folder prop runs in" in r.err, r.err
    assert "PYTHONPATH" in r.err and len(r.err.strip().splitlines()) == 1


def test_an_mlp_still_refuses_another_input_shape(tmp_path, cli):
    from tests.conftest import write_user_data

    rng = np.random.default_rng(1)
    write_user_data(tmp_path, 40, rng)
    write_keys(tmp_path, ("k.bin",), rng)
    r = cli("personalize", tmp_path / "model.safetensors", "--data", tmp_path / "mine.npz", "--key-file",
            tmp_path / "k.bin", "--out", tmp_path / "b", *FAST)  # fmt: skip
    assert r.code == 0, r.err
    np.save(tmp_path / "x5.npy", np.zeros((3, 5), np.float32))
    r = cli("run", tmp_path / "b", "--input", tmp_path / "x5.npy", "--output", tmp_path / "y.npy")
    assert r.code == 2 and "the bundle expects (4,)" in r.err and not (tmp_path / "y.npy").exists()
