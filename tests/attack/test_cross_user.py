"""Cross-user rows: only users of the bundle get one, gated beyond what that user's own behaviour explains."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from prop_cli.api import KeySource, add_user, personalize_checkpoint
from prop_cli.config import PersonalizeConfig
from prop_cli.core.key_files import read_key_file
from tests.conftest import write_keys, write_user_data

FAST = ["--probes", "null,random,cross-user", "--random", "64", "--samples", "64"]


@pytest.fixture(scope="module")
def two_users(tmp_path_factory) -> Path:
    """Two users whose preferences overlap (user 2 negates a little less), sealed and unsealed."""
    d = tmp_path_factory.mktemp("cross")
    rng = np.random.default_rng(3)
    write_user_data(d, 300, rng)  # user 1: y = -0.5 x[:, :2]
    x = rng.uniform(-1, 1, (300, 4)).astype(np.float32)
    np.savez(d / "bob.npz", x=x, y=(-0.4 * x[:, :2]).astype(np.float32))
    write_keys(d, ("k.bin", "bob.bin", "stranger.bin"), rng)
    me, bob = (KeySource(read_key_file(d / n), "file") for n in ("k.bin", "bob.bin"))
    ckpt = str(d / "model.safetensors")
    sealed = PersonalizeConfig.of(steps=300, seal=True)
    personalize_checkpoint(ckpt, [(d / "mine.npz", me)], d / "sealed.prop", sealed)
    add_user(d / "sealed.prop", d / "bob.npz", bob, cfg=PersonalizeConfig.of(steps=300, seal=True))
    cfg = PersonalizeConfig.of(steps=300)
    personalize_checkpoint(ckpt, [(d / "mine.npz", me), (d / "bob.npz", bob)], d / "two.prop", cfg)
    return d


def _attack(cli, d: Path, bundle: str, *keys: str, max_leak: str = "0.05"):
    args = [a for k in keys for a in ("--key-file", d / k)]
    gate = ["--max-leak", max_leak, "--json", "-"]
    r = cli("attack", d / bundle, "--data", d / "mine.npz", *args, *FAST, *gate)
    return r, json.loads(r.out)


def test_a_sealed_bundle_with_two_overlapping_users_passes(two_users, cli):
    r, rep = _attack(cli, two_users, "sealed.prop", "k.bin", "bob.bin")
    assert r.code == 0, r.err
    u2 = next(g for g in rep["groups"] if g["name"] == "user 2")
    # Bob's key shows much of my behaviour (he asked for nearly the same): raw, it would fail ...
    assert u2["threat"] == "cross-user" and u2["leakage"]["worst"] > 0.5
    # ... but it is his own record, trained on his data alone: that is the control, nothing beyond it.
    assert u2["enrolment"] == {"how": "it opens another user's record", "yours": False, "independent": True}
    assert "own record" in u2["control"]["model"] and u2["beyond"] == 0
    assert rep["max_leak"]["passed"] is True and rep["bundle"]["users"] == 2


def test_a_key_that_is_no_user_is_a_plain_key_row_and_one_warning(two_users, cli):
    r, rep = _attack(cli, two_users, "sealed.prop", "k.bin", "stranger.bin")
    assert r.code == 0, r.err
    names = [g["name"] for g in rep["groups"]]
    assert "user 2" not in names and "key 2" in names
    k2 = rep["groups"][names.index("key 2")]
    assert k2["threat"] == "T0" and k2["control"]["leakage"]["worst"] == 0
    warned = [w for w in rep["warnings"] if "--key-file 2 is not a user of this bundle" in w]
    assert len(warned) == 1 and "opens none of the bundle's records" in warned[0]
    assert "prop: warning: --key-file 2 is not a user" in r.err


def test_your_own_key_as_another_user_fails(two_users, cli):
    """A second key that opens *your* record shows your behaviour: its control is the reference."""
    r, rep = _attack(cli, two_users, "sealed.prop", "k.bin", "k.bin")
    assert r.code == 1
    assert rep["max_leak"]["failing"] == ["user 2"]
    assert "it is your key, or opens your record" in rep["max_leak"]["verdict"]


def test_unsealed_users_are_told_by_behaviour_and_cannot_be_controlled(two_users, cli):
    r, rep = _attack(cli, two_users, "two.prop", "k.bin", "bob.bin", "stranger.bin", max_leak="0.99")
    rows = {g["name"]: g for g in rep["groups"]}
    assert rows["user 2"]["enrolment"]["how"].startswith("its outputs move")
    assert rows["user 2"]["control"] == {"available": False, "reason": rows["user 2"]["control"]["reason"]}
    assert "share one encoder" in rows["user 2"]["control"]["reason"]
    assert rows["user 2"]["gate"]["why"] == "no control"
    assert rows["key 3"]["threat"] == "T0"  # the stranger: moves like a random key
