"""The base-drift probe (issue 42): an unsealed bundle's base moves where the user's data lies, and
--freeze-base keeps it the original's. On a small IL example: a user whose data fills one quadrant of the
positions, and one whose data fills the whole state space."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from prop_cli.api import KeySource, personalize_checkpoint
from prop_cli.attack.probes.drift import beyond_chance, chance, one_sided
from prop_cli.config import PersonalizeConfig
from prop_cli.core.key_files import read_key_file
from tests.conftest import write_keys


@pytest.fixture(scope="module")
def il(tmp_path_factory) -> Path:
    from examples.il_task import write_example

    d = tmp_path_factory.mktemp("drift")
    paths = write_example(d, seed=0, base_samples=4000, user_samples=1200, base_steps=300)
    mine = np.load(paths["mine"])
    x, y = mine["x"], mine["y"]
    quadrant = (x[:, 0] > 0) & (x[:, 1] > 0)
    np.savez(d / "quad.npz", x=x[quadrant], y=y[quadrant])
    write_keys(d, ("k.bin",), np.random.default_rng(1))
    key = KeySource(read_key_file(d / "k.bin"), "file")
    for name, data, frozen in (("quad", "quad", False), ("frozen", "quad", True), ("whole", "mine", False)):
        cfg = PersonalizeConfig.of(steps=200, freeze_base=frozen)
        personalize_checkpoint(str(paths["base"]), [(d / f"{data}.npz", key)], d / f"{name}.prop", cfg)
    return d


def _drift(cli, d: Path, bundle: str, data: str, *extra: str):
    r = cli("attack", d / f"{bundle}.prop", "--data", d / f"{data}.npz", "--key-file", d / "k.bin",
            "--original", d / "base.safetensors", "--probes", "drift", *extra, "--json", "-")  # fmt: skip
    rep = json.loads(r.out) if r.out.strip().startswith("{") else None
    return r, rep, (rep["groups"][0] if rep and rep["groups"] else None)


def test_the_drift_of_a_default_bundle_points_at_the_users_quadrant(il, cli):
    r, rep, row = _drift(cli, il, "quad", "quad", "--max-leak", "0.05")
    assert r.code == 1, r.err
    assert rep["max_leak"]["failing"] == ["drift"]
    assert "points at where your data lies" in rep["max_leak"]["verdict"]
    s = row["search"]
    assert s["layer"] == "0" and s["weight_change"] > 0 and len(s["singular_values"]) == 3
    # The top singular vector (the attacker's pick) has nearly every sample on one side of it...
    assert row["search"]["best_restart"] == 0 and s["one_sided"][0] > 0.7
    # ... far beyond a random direction's, on average.
    c = row["control"]
    assert c["available"] and "random input directions" in c["model"]
    assert row["beyond"] > 0.3
    assert row["gate"] == {"on": "beyond-control", "value": row["beyond"], "why": None}


def test_freeze_base_leaves_nothing_to_read(il, cli):
    r, rep, row = _drift(cli, il, "frozen", "quad", "--max-leak", "0.05")
    assert r.code == 0, r.err
    assert row["search"]["weight_change"] == 0 and row["search"]["one_sided"] == [0.0, 0.0, 0.0]
    assert row["fidelity"]["worst"] == 0  # the no-key model is the original, bit for bit
    assert row["beyond"] == 0 and rep["max_leak"]["passed"]


def test_a_user_whose_data_fills_the_inputs_is_not_located(il, cli):
    """The base moved (its outputs too), but along no side of the inputs that your data prefers."""
    r, rep, row = _drift(cli, il, "whole", "mine", "--max-leak", "0.05")
    assert r.code == 0, r.err
    assert row["search"]["weight_change"] > 0 and row["fidelity"]["mean"] > 0
    assert row["beyond"] <= 0.05


def test_the_drift_probe_needs_the_original(il, cli):
    d = il
    base = ["attack", d / "quad.prop", "--data", d / "quad.npz", "--key-file", d / "k.bin"]
    r = cli(*base, "--probes", "drift")
    assert r.code == 2 and r.err.startswith("prop: error: --probes drift need the original checkpoint"), r.err
    assert "--original" in r.err and "Traceback" not in r.err
    r = cli(*base, "--probes", "null,drift", "--original", d / "base.safetensors", "--json", "-")
    assert [g["name"] for g in json.loads(r.out)["groups"]] == ["null", "drift"]
    # A default audit without the original runs every other default probe, and lists what ran.
    r = cli(*base, "--probes", "null", "--json", "-")
    assert "drift" not in json.loads(r.out)["settings"]["probes"]


def test_one_sided_counts_samples_beyond_chance():
    x = torch.tensor([[1.0, 0.0], [2.0, 1.0], [3.0, 1.0], [-1.0, 1.0]])
    dirs = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    # along x: 3 of 4 on the positive side; along y too, the 4th on the hyperplane (on neither side)
    torch.testing.assert_close(one_sided(x, dirs), torch.tensor([0.5, 0.5]))
    assert chance(256) == pytest.approx(1.96 / 16)
    scored, raw = beyond_chance(torch.ones(400, 2), dirs)
    torch.testing.assert_close(raw, torch.tensor([1.0, 1.0]))
    torch.testing.assert_close(scored, torch.tensor([1.0 - 1.96 / 20] * 2))
