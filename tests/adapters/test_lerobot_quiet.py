"""A LeRobot user's first commands (issue 41, the newcomer list): LeRobot's own chatter stays out of
prop's output (from_pretrained prints "Loading weights from local directory" on stdout at every local
load; prop shows it with PROP_DEBUG only, and then on stderr, as stdout holds results); `prop eval`
without the --obs-map the policy needs says so before any rollout."""

from __future__ import annotations

import signal
import sys

import numpy as np
import pytest

pytest.importorskip("lerobot")
pytestmark = pytest.mark.lerobot

from examples import lerobot_reach_task as task  # noqa: E402
from prop_cli.cli.main import main  # noqa: E402

CHATTER = "Loading weights from local directory"


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    d = tmp_path_factory.mktemp("quiet")
    task.record(d / "data", 2, 0, np.zeros(3, np.float32))
    task.train_base(d / "data", d / "act", steps=2)
    (d / "k.bin").write_bytes(bytes(range(16)))
    (d / "k.bin").chmod(0o600)
    return d


@pytest.fixture(scope="module")
def bundle(work):
    """An unsealed bundle of the ACT, made as a user makes it (prop personalize)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(sys, "argv", ["prop", "personalize", str(work / "act"), "--data", str(work / "data"),
                                 "--key-file", str(work / "k.bin"), "--out", str(work / "bundle"), "--steps",
                                 "2", "--report-budget", "4"])  # fmt: skip
        sigint = signal.getsignal(signal.SIGINT)  # main() leaves its exit-time handler behind
        with pytest.raises(SystemExit) as e:
            main()
        signal.signal(signal.SIGINT, sigint)
    assert e.value.code in (0, None)
    return work / "bundle"


def test_loading_a_policy_folder_prints_no_lerobot_line(work, cli, monkeypatch):
    monkeypatch.delenv("PROP_DEBUG", raising=False)
    r = cli("inspect", work / "act")
    assert r.code == 0 and "lerobot adapter" in r.out, r.err
    assert CHATTER not in r.out and CHATTER not in r.err
    r = cli("personalize", work / "act", "--data", work / "data", "--key-file", work / "k.bin", "--out",
            work / "b.prop", "--steps", "2", "--report-budget", "4", "--json")  # fmt: skip
    assert r.code == 0, r.err
    assert CHATTER not in r.out and CHATTER not in r.err and r.out.startswith("{")
    r = cli("run", work / "b.prop", "--input", work / "data", "--key-file", work / "k.bin", "--output",
            work / "y.npy")  # fmt: skip
    assert r.code == 0 and CHATTER not in r.out + r.err, r.err


def test_prop_debug_shows_it_on_stderr(work, cli, monkeypatch):
    monkeypatch.setenv("PROP_DEBUG", "1")
    r = cli("inspect", work / "act", "--json")
    assert r.code == 0 and CHATTER in r.err and CHATTER not in r.out, r.err


@pytest.mark.parametrize(
    "obs_map, words",
    [
        (None, "the environment's observation has no 'observation.state'"),
        ("observation.stat=observation", "(--obs-map's 'observation.stat': not a feature the policy takes)"),
    ],
)
def test_eval_finds_a_missing_obs_map_before_any_rollout(bundle, cli, obs_map, words):
    args = ["eval", bundle, "--env", task.ENV_ID, "--episodes", "1", "--random-keys", "1",
            "--max-steps", "2", *(["--obs-map", obs_map] if obs_map else [])]  # fmt: skip
    r = cli(*args)
    assert r.code == 2 and words in r.err and len(r.err.strip().splitlines()) == 1, r.err
    assert "eval:" not in r.err  # no condition started

