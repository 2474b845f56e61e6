"""Model folders (config.json + model.safetensors): --arch, registered builders, bad input."""

from __future__ import annotations

import json
import uuid
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file

from prop_adapters import load_checkpoint
from prop_adapters.folder import ENTRY_POINT_GROUP
from prop_cli.bundle import load_bundle
from prop_cli.errors import PropError
from tests.conftest import FAST

POLICIES = """
from torch import nn


class Policy(nn.Module):
    def __init__(self, sizes, scale=1.0):
        super().__init__()
        self.input_shape = (sizes[0],)
        self.body = nn.Sequential(nn.Linear(sizes[0], sizes[1]), nn.ReLU(), nn.Linear(sizes[1], sizes[1]))
        self.head = nn.Linear(sizes[1], sizes[2])
        self.scale = scale

    def forward(self, x):
        return self.head(nn.functional.relu(self.body(x))) * self.scale


def build(config, scale=1.0):
    return Policy(config["sizes"], scale)
"""


@pytest.fixture
def pkg(tmp_path, monkeypatch) -> str:
    """An importable package (unique name) with ``policies.build(config)``; cwd is its parent."""
    name = f"my_pkg_{uuid.uuid4().hex[:8]}"
    root = tmp_path / "site"
    (root / name).mkdir(parents=True)
    (root / name / "__init__.py").write_text("")
    (root / name / "policies.py").write_text(POLICIES)
    monkeypatch.syspath_prepend(str(root))
    monkeypatch.chdir(tmp_path)
    return name


def _policy(pkg: str, sizes=(4, 16, 2)) -> torch.nn.Module:
    import importlib

    torch.manual_seed(0)
    return importlib.import_module(f"{pkg}.policies").build({"sizes": list(sizes)})


def make_folder(path: Path, pkg: str, type_: str | None = "tinypolicy", sizes=(4, 16, 2)) -> Path:
    path.mkdir()
    config = {"sizes": list(sizes), **({"type": type_} if type_ else {})}
    (path / "config.json").write_text(json.dumps(config))
    state = {k: v.contiguous() for k, v in _policy(pkg, sizes).state_dict().items()}
    save_file(state, str(path / "model.safetensors"))
    return path


def register(tmp_path: Path, type_: str, value: str) -> None:
    """Install (on sys.path) a distribution registering ``type_`` in prop's entry-point group."""
    dist = tmp_path / "site" / f"reg_{uuid.uuid4().hex[:8]}-0.1.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist.name.split('-')[0]}\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(f"[{ENTRY_POINT_GROUP}]\n{type_} = {value}\n")


def test_arch_inspect_personalize_run(cli, pkg, tmp_path, workdir):
    folder = make_folder(tmp_path / "my_policy", pkg)
    arch = f"{pkg}.policies:build"
    r = cli("inspect", "./my_policy/", "--arch", arch, "--json")
    assert r.code == 0, r.err
    info = json.loads(r.out)
    assert info["adapter"] == "folder" and info["input_shape"] == [4]
    assert [x["name"] for x in info["layers"]] == ["body.0", "body.2", "head"]

    out = tmp_path / "mine.prop"
    r = cli(
        "personalize", "./my_policy/", "--arch", arch, "--arch-kwargs", '{"scale": 2.0}',
        "--data", workdir / "mine.npz", "--key-file", workdir / "k.bin", "--out", out, *FAST,
    )  # fmt: skip
    assert r.code == 0, r.err
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["model"] == {
        "adapter": "folder",
        "arch": arch,
        "arch_kwargs": {"scale": 2.0},
        "builder": "--arch",
        "config": {"sizes": [4, 16, 2], "type": "tinypolicy"},
    }
    original = load_file(str(folder / "model.safetensors"))
    base = load_file(str(out / "base.safetensors"))
    assert {k: v.shape for k, v in base.items()} == {k: v.shape for k, v in original.items()}
    with pytest.raises(PropError, match=r"model\.arch .*--trust-remote-code"):
        load_bundle(out)  # the bundle names its factory: --arch was consent for personalize only
    bundle = load_bundle(out, trust_remote_code=True)  # from the manifest's config: no folder needed
    x = torch.from_numpy(np.load(workdir / "x.npy"))
    ref = _policy(pkg)
    ref.load_state_dict(base)
    with torch.no_grad():
        torch.testing.assert_close(bundle.keyed.module(x), ref(x) * 2.0)
    r = cli("run", out, "--input", workdir / "x.npy", "--output", tmp_path / "y.npy")
    assert r.code == 2 and "--trust-remote-code" in r.err and r.err.count("\n") == 1
    assert not (tmp_path / "y.npy").exists()
    r = cli("run", out, "--input", workdir / "x.npy", "--output", tmp_path / "y.npy", "--trust-remote-code")
    assert r.code == 0, r.err


def test_registered_entry_point_builds_without_arch(cli, pkg, tmp_path):
    make_folder(tmp_path / "f", pkg, type_="tiny_registered")
    register(tmp_path, "tiny_registered", f"{pkg}.policies:build")
    with pytest.raises(PropError, match="entry point 'tiny_registered' that config.json selects"):
        load_checkpoint(tmp_path / "f")  # config.json chooses which installed code runs: consent first
    loaded = load_checkpoint(tmp_path / "f", trust_remote_code=True)
    assert loaded.spec["builder"] == "entry point 'tiny_registered'"
    assert loaded.spec["arch"] == f"{pkg}.policies:build"
    x = torch.randn(3, 4)
    with torch.no_grad():
        torch.testing.assert_close(loaded.module(x), _policy(pkg)(x))
    r = cli("inspect", tmp_path / "f")
    assert r.code == 2 and "--trust-remote-code" in r.err
    r = cli("inspect", tmp_path / "f", "--trust-remote-code")
    assert r.code == 0 and "folder adapter" in r.out, r.err


def test_model_type_field_and_frozen_base_copies_the_file(cli, pkg, tmp_path, workdir):
    folder = make_folder(tmp_path / "hf", pkg, type_=None)
    cfg = json.loads((folder / "config.json").read_text())
    (folder / "config.json").write_text(json.dumps({**cfg, "model_type": "tiny_hf"}))
    register(tmp_path, "tiny_hf", f"{pkg}.policies:build")
    out = tmp_path / "frozen.prop"
    r = cli(
        "personalize", folder, "--freeze-base", "--data", workdir / "mine.npz",
        "--key-file", workdir / "k.bin", "--out", out, "--trust-remote-code", *FAST,
    )  # fmt: skip
    assert r.code == 0, r.err
    assert (out / "base.safetensors").read_bytes() == (folder / "model.safetensors").read_bytes()


def test_sharded_weights(pkg, tmp_path):
    folder = make_folder(tmp_path / "sh", pkg)
    state = load_file(str(folder / "model.safetensors"))
    (folder / "model.safetensors").unlink()
    names = sorted(state)
    half = {n: state[n] for n in names[:3]}, {n: state[n] for n in names[3:]}
    weight_map = {}
    for i, part in enumerate(half):
        save_file(part, str(folder / f"model-0000{i + 1}-of-00002.safetensors"))
        weight_map.update(dict.fromkeys(part, f"model-0000{i + 1}-of-00002.safetensors"))
    (folder / "model.safetensors.index.json").write_text(json.dumps({"weight_map": weight_map}))
    loaded = load_checkpoint(folder, arch=f"{pkg}.policies:build")
    assert set(loaded.module.state_dict()) == set(state)


def test_bare_weights_folder_reads_as_the_file(tmp_path):
    from tests.conftest import make_mlp_checkpoint

    (tmp_path / "bare").mkdir()
    make_mlp_checkpoint(tmp_path / "bare" / "model.safetensors")
    loaded = load_checkpoint(tmp_path / "bare")
    assert loaded.spec["adapter"] == "mlp" and loaded.source.endswith("model.safetensors")


# ---- bad input: one line, exit 2, nothing written -----------------------------------------------


def _bad(cli, tmp_path, workdir, path, *extra) -> str:
    out = tmp_path / "never.prop"
    r = cli("inspect", path, *extra)
    assert r.code == 2 and r.err.count("\n") == 1 and r.err.startswith("prop: error:"), r.err
    r2 = cli(
        "personalize", path, "--data", workdir / "mine.npz", "--key-file", workdir / "k.bin",
        "--out", out, *extra, *FAST,
    )  # fmt: skip
    assert r2.code == 2 and r2.err.strip() == r.err.strip() and not out.exists(), r2.err
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".never")]
    return r.err


def test_folder_without_weights(cli, pkg, tmp_path, workdir):
    folder = make_folder(tmp_path / "f", pkg)
    (folder / "model.safetensors").unlink()
    err = _bad(cli, tmp_path, workdir, folder, "--arch", f"{pkg}.policies:build")
    assert "has no weights (model.safetensors" in err
    (tmp_path / "empty").mkdir()
    assert "has no config.json" in _bad(cli, tmp_path, workdir, tmp_path / "empty")


def test_config_type_without_builder(cli, pkg, tmp_path, workdir):
    folder = make_folder(tmp_path / "f", pkg, type_="nobody_builds_this")
    err = _bad(cli, tmp_path, workdir, folder)
    assert "no builder for config type 'nobody_builds_this'" in err and ENTRY_POINT_GROUP in err
    assert "--arch" in err
    untyped = make_folder(tmp_path / "g", pkg, type_=None)
    assert "has no 'type' or 'model_type'" in _bad(cli, tmp_path, workdir, untyped)


def test_weights_that_do_not_fit_and_wrong_flags(cli, pkg, tmp_path, workdir):
    folder = make_folder(tmp_path / "f", pkg)
    (folder / "config.json").write_text(json.dumps({"type": "x", "sizes": [4, 8, 2]}))
    err = _bad(cli, tmp_path, workdir, folder, "--arch", f"{pkg}.policies:build")
    assert "does not fit" in err and "shape mismatch" in err
    err = _bad(cli, tmp_path, workdir, make_folder(tmp_path / "g", pkg), "--activation", "tanh")
    assert "--activation does not apply to a model folder" in err
    (tmp_path / "h").mkdir()
    (tmp_path / "h" / "config.json").write_text("[1, 2]")
    (tmp_path / "h" / "model.safetensors").write_bytes(b"")
    with pytest.raises(PropError, match="not a JSON object"):
        load_checkpoint(tmp_path / "h")


def test_factory_that_does_not_take_config(pkg, tmp_path):
    folder = make_folder(tmp_path / "f", pkg)
    with pytest.raises(PropError, match=r"factory\(config, \*\*arch_kwargs\) failed"):
        load_checkpoint(folder, arch="torch.nn:Linear")
