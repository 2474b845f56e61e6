"""LeRobot policy bundles written by prop 0.1.0 still load and give the same action chunks (issue 28; pytest
-m lerobot, in .venv-lerobot): within v01.TOLERANCE of those stored on the machine that wrote them, and bit
for bit between the runs that give the base here (issue 41).

tests/fixtures/bundles-0.1/lerobot-*: a tiny ACT, Diffusion Policy and SmolVLA (examples/smolvla_tiny.py),
unsealed and sealed, that prop 0.1.0 (commit f7777f7) personalized, and the action chunks `prop run`
gave on a recorded PandaReach episode with the user's key, no key, a key one bit off and a key enrolled
in nothing (tests/fixtures/make_v01_bundles.py --lerobot). Only what a user of 0.1.0 had is used: the
`prop` command and prop_cli.api.load_bundle. The other adapters: tests/bundle/test_old_bundles.py.
"""

from __future__ import annotations

import pytest

pytest.importorskip("lerobot")
pytestmark = pytest.mark.lerobot

from prop_cli.api import load_bundle  # noqa: E402
from tests.fixtures import v01  # noqa: E402

NAMES = v01.names(lerobot=True)


def _fixture(name: str) -> v01.Fixture:
    fx = v01.load(name)
    if fx.meta["policy"] == "smolvla":
        pytest.importorskip("num2words")  # SmolVLM's processor (scripts/setup-lerobot.sh installs it)
    return fx


def test_the_fixtures_cover_each_policy_unsealed_and_sealed():
    metas = [v01.load(n).meta for n in NAMES]
    assert {(m["policy"], m["mode"]) for m in metas} == {
        (p, mode) for p in ("act", "diffusion", "smolvla") for mode in ("unsealed", "sealed")
    }
    assert all(m["written_by"]["prop"] == "prop-keys 0.1.0" for m in metas)


@pytest.mark.parametrize("name", NAMES)
def test_the_bundle_holds_the_files_prop_0_1_wrote_and_loads(name):
    fx = _fixture(name)
    assert fx.bundle_files() == fx.meta["files"]
    bundle = load_bundle(fx.bundle)
    assert bundle.path == fx.bundle


@pytest.mark.parametrize("name", NAMES)
def test_prop_run_gives_the_same_action_chunks(name, cli, tmp_path, monkeypatch):
    fx = _fixture(name)
    assert {r["name"] for r in fx.runs} >= {"user", "none", "near", "wrong"}
    v01.check_tolerance_tells_keyed_from_base(fx, fx.runs)
    v01.check_prop_run(fx, fx.runs, cli, tmp_path, monkeypatch)


@pytest.mark.parametrize("name", NAMES)
def test_prop_inspect_describes_the_bundle_as_0_1_did(name, cli):
    v01.check_inspect(_fixture(name), cli)
