"""What a new user met first (issue 41, the newcomer list): each item as the user typed it."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import FAST, make_mlp_checkpoint

LONG = "policy_network.feature_extractor.layers."  # keyed-layer names long enough to pass 100 columns


@pytest.fixture
def long_bundle(workdir, cli):
    """A 13-layer MLP whose 12 keyed layers' names make a ~550-character keyed-layers row."""
    make_mlp_checkpoint(workdir / "long.safetensors", sizes=(4, *[16] * 12, 2), prefix=LONG)
    r = cli("personalize", workdir / "long.safetensors", "--data", workdir / "mine.npz", "--key-file",
            workdir / "k.bin", "--out", workdir / "long.prop", "--steps", "5", "--device", "cpu")  # fmt: skip
    assert r.code == 0, r.err
    return workdir / "long.prop"


@pytest.mark.parametrize("what", ["long.prop", "long.safetensors"])
def test_inspect_wraps_to_columns(long_bundle, cli, monkeypatch, what):
    monkeypatch.setenv("COLUMNS", "100")
    r = cli("inspect", long_bundle.parent / what)
    assert r.code == 0, r.err
    lines = r.out.splitlines()
    assert max(len(line.rstrip()) for line in lines) <= 100, r.out
    # Wrapped, not cut: every keyed layer's name is there in full.
    text = "".join(line.replace("│", "").replace(" ", "") for line in lines)
    for i in range(2, 25, 2):
        assert f"{LONG}{i}" in text


def test_inspect_without_columns_keeps_each_row_on_one_line(long_bundle, cli, monkeypatch):
    monkeypatch.delenv("COLUMNS", raising=False)  # piped, nothing asked: one line per row (for grep)
    r = cli("inspect", long_bundle)
    row = [line for line in r.out.splitlines() if "keyed layers" in line]
    assert len(row) == 1 and f"{LONG}2, " in row[0] and f"{LONG}24" in row[0]


def test_a_bundles_manifest_names_its_bundle(workdir, cli, monkeypatch):
    r = cli("personalize", workdir / "model.safetensors", "--data", workdir / "mine.npz", "--key-file",
            workdir / "k.bin", "--out", workdir / "mine.prop", *FAST)  # fmt: skip
    assert r.code == 0, r.err
    manifest = workdir / "mine.prop" / "manifest.json"
    r = cli("run", manifest, "--input", workdir / "x.npy", "--key-file", workdir / "k.bin", "--output",
            workdir / "y.npy")  # fmt: skip
    assert r.code == 0, r.err
    r2 = cli("run", workdir / "mine.prop", "--input", workdir / "x.npy", "--key-file", workdir / "k.bin",
             "--output", workdir / "y2.npy")  # fmt: skip
    assert r2.code == 0 and np.array_equal(np.load(workdir / "y.npy"), np.load(workdir / "y2.npy"))
    r = cli("inspect", manifest, "--json")
    assert r.code == 0 and '"mode": "unsealed"' in r.out, r.err
    monkeypatch.chdir(workdir / "mine.prop")  # from inside the bundle: manifest.json is "."
    r = cli("run", "manifest.json", "--input", workdir / "x.npy", "--output", workdir / "y0.npy")
    assert r.code == 0, r.err


def test_only_a_manifest_json_file_names_its_folder(workdir, cli):
    """Any other file inside a bundle, or a folder called manifest.json, is not taken for the bundle."""
    r = cli("personalize", workdir / "model.safetensors", "--data", workdir / "mine.npz", "--key-file",
            workdir / "k.bin", "--out", workdir / "mine.prop", *FAST)  # fmt: skip
    assert r.code == 0, r.err
    (workdir / "manifest.json").mkdir()
    for path in (workdir / "mine.prop" / "base.safetensors", workdir / "manifest.json"):
        r = cli("run", path, "--input", workdir / "x.npy", "--output", workdir / "y.npy")
        assert r.code == 2 and "not a prop bundle" in r.err, r.err


def test_the_library_names_the_folder_to_give(workdir, cli):
    from prop_cli.api import load_bundle
    from prop_cli.errors import PropError

    r = cli("personalize", workdir / "model.safetensors", "--data", workdir / "mine.npz", "--key-file",
            workdir / "k.bin", "--out", workdir / "mine.prop", *FAST)  # fmt: skip
    assert r.code == 0, r.err
    with pytest.raises(PropError, match="give the bundle folder .*mine.prop"):
        load_bundle(workdir / "mine.prop" / "manifest.json")
