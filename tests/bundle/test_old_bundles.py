"""Bundles written by prop 0.1.0 still load and give the same outputs (issue 28), within v01.TOLERANCE of
the outputs stored on the machine that wrote them; bit for bit between runs computed here (issue 41).

tests/fixtures/bundles-0.1 holds bundles that prop 0.1.0 (commit f7777f7) wrote, of each mode (unsealed,
hardened, sealed with each payload kind, passphrase users, users added with add-user) and adapter (plain
MLP, Stable-Baselines3 PPO, an --arch module, a model folder), two with an ONNX export, and the outputs
`prop run` gave with the user's key, no key, a key one bit off and a key enrolled in nothing
(tests/fixtures/make_v01_bundles.py; those two keys now run only with --allow-unenrolled-key, and then
give the base's outputs, as 0.1's did). Only what a user of 0.1.0 had is used here: the `prop` command
and prop_cli.api's load_bundle, run_bundle and read_key_file. The LeRobot policies:
tests/adapters/test_lerobot_old_bundles.py.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from prop_cli.api import load_bundle, read_key_file, run_bundle
from tests.fixtures import v01

NAMES = v01.names(lerobot=False)


@pytest.fixture(autouse=True)
def _in_the_repository_root(monkeypatch):
    # The --arch file paths the module bundles record are relative to the folder prop runs in.
    monkeypatch.chdir(v01.ROOT)
    monkeypatch.delenv("PROP_PASSPHRASE", raising=False)


def test_the_fixtures_cover_each_mode_and_adapter():
    metas = [v01.load(n).meta for n in NAMES]
    kinds = {(m["adapter"], m["mode"]) for m in metas}
    assert {("mlp", "unsealed"), ("mlp", "sealed"), ("sb3", "unsealed"), ("sb3", "sealed"),
            ("module", "unsealed"), ("module", "sealed"), ("folder", "unsealed")} <= kinds  # fmt: skip
    payloads = {m.get("payload") for m in metas if m["mode"] == "sealed"}
    assert payloads >= {"lora", "delta", "full", "peft-lora"}
    assert any(m.get("hardened") for m in metas)
    assert {m["mode"] for m in metas if m.get("onnx")} == {"unsealed", "sealed"}
    runs = [r for m in metas for r in m["runs"]]
    assert any(r["passphrase"] for r in runs) and any(r["onnx"] for r in runs)
    assert all(m["written_by"]["prop"] == "prop-keys 0.1.0" for m in metas)


@pytest.mark.parametrize("name", NAMES)
def test_the_bundle_holds_the_files_prop_0_1_wrote(name):
    fx = v01.load(name)
    assert fx.bundle_files() == fx.meta["files"]


@pytest.mark.parametrize("name", NAMES)
def test_load_bundle_and_run_bundle_give_the_same_outputs(name, tmp_path):
    fx = v01.load(name)
    bundle = load_bundle(fx.bundle, trust_remote_code=fx.trust)
    x = np.load(fx.input, allow_pickle=False)
    runs = [r for r in fx.runs if not r["onnx"] and not r["passphrase"]]  # passphrases: the CLI test
    assert {r["name"] for r in runs} >= {"user", "none", "near", "wrong"}
    v01.check_tolerance_tells_keyed_from_base(fx, runs)
    outputs = {}
    for run in runs:
        key = read_key_file(fx.key(run["key_file"], tmp_path)) if run["key_file"] else None
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # near and wrong: enrolled in nothing, the base runs (warned)
            y = run_bundle(bundle, x, key, allow_unenrolled=v01.unenrolled(run))
            again = run_bundle(bundle, x, key, allow_unenrolled=v01.unenrolled(run))
        expected = fx.expected(run)
        assert v01.close(y, expected), (run["name"], v01.gap(y, expected))
        assert v01.same(y, again), run["name"]  # one process, one machine: the same bits
        outputs[run["name"]] = y
    v01.check_base_runs_agree(outputs)


@pytest.mark.parametrize("name", NAMES)
def test_prop_run_gives_the_same_outputs(name, cli, tmp_path, monkeypatch):
    """`prop run` with the user's key, a key enrolled in nothing (allowed: the base runs, warned) and every
    passphrase (the API test above runs each key file; a `prop run` costs ~0.1 s of typer set-up)."""
    fx = v01.load(name)
    runs = [r for r in fx.runs if not r["onnx"] and (r["passphrase"] or r["name"] in ("user", "wrong"))]
    v01.check_prop_run(fx, runs, cli, tmp_path, monkeypatch)


@pytest.mark.parametrize("name", [n for n in NAMES if v01.load(n).meta.get("onnx")])
def test_prop_run_onnx_gives_the_same_outputs(name, cli, tmp_path, monkeypatch):
    """The bundle's ONNX export through `prop run --onnx`, within the tolerance: the expected outputs came
    from these very graphs, run by onnxruntime on another CPU (its kernels too pick code by vector unit)."""
    pytest.importorskip("onnxruntime")
    fx = v01.load(name)
    v01.check_prop_run(fx, [r for r in fx.runs if r["onnx"]], cli, tmp_path, monkeypatch)


@pytest.mark.parametrize("name", NAMES)
def test_prop_inspect_describes_the_bundle_as_0_1_did(name, cli):
    v01.check_inspect(v01.load(name), cli)
