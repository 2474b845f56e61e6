"""`prop eval`'s --env and observations checked before any rollout (issue 41, the newcomer list): a
mistyped factory name is named as such, and an observation the bundle cannot take is reported before the
first episode starts."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import FAST, make_mlp_checkpoint

pytest.importorskip("gymnasium")

MY_ENVS = '''
import gymnasium as gym
import numpy as np


class DictObs(gym.Env):
    """Pendulum-sized, but its observations are dicts (as robot simulators give them)."""

    def __init__(self):
        box = gym.spaces.Box(-1, 1, (3,), np.float32)
        self.observation_space = gym.spaces.Dict({"state": box})
        self.action_space = gym.spaces.Box(-2, 2, (1,), np.float32)

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        return {"state": np.zeros(3, np.float32)}, {}

    def step(self, action):
        raise AssertionError("no step: the observation is refused before any rollout")


def make():
    return gym.make("Pendulum-v1")


def make_dict():
    return DictObs()
'''


@pytest.fixture
def bundle(tmp_path, cli, monkeypatch):
    """An MLP bundle for 3 observations and 1 action, and my_envs.py beside it."""
    rng = np.random.default_rng(0)
    make_mlp_checkpoint(tmp_path / "pi.safetensors", sizes=(3, 8, 1))
    x = rng.uniform(-1, 1, (100, 3)).astype(np.float32)
    np.savez(tmp_path / "mine.npz", x=x, y=x[:, :1])
    (tmp_path / "k.bin").write_bytes(bytes(range(16)))
    (tmp_path / "k.bin").chmod(0o600)
    (tmp_path / "my_envs.py").write_text(MY_ENVS)
    monkeypatch.chdir(tmp_path)
    r = cli("personalize", "pi.safetensors", "--data", "mine.npz", "--key-file", "k.bin", "--out", "b", *FAST)
    assert r.code == 0, r.err
    return tmp_path


QUICK = ["--episodes", "1", "--max-steps", "2", "--random-keys", "1", "--episodes-per-key", "1"]


@pytest.mark.parametrize(
    "env, message",
    [
        ("my_envs:mak", "my_envs has no 'mak' and registers no gymnasium id 'mak'; did you mean --env "
                        "my_envs:make?"),  # fmt: skip
        ("my_envs.py:make_dik", "my_envs.py has no 'make_dik'; did you mean --env my_envs.py:make_dict?"),
        ("gymnasium:Pendulum-v9", "did you mean --env gymnasium:Pendulum-v1?"),
    ],
)
def test_a_mistyped_name_after_the_colon_says_what_was_meant(bundle, cli, env, message):
    r = cli("eval", "b", "--env", env, *QUICK)
    assert r.code == 2 and message in r.err, r.err
    assert len(r.err.strip().splitlines()) == 1 and "gymnasium cannot make it" not in r.err


def test_a_name_nothing_is_close_to_is_still_gymnasiums_to_judge(bundle, cli):
    r = cli("eval", "b", "--env", "my_envs:Xyzzy-v0", *QUICK)
    assert r.code == 2 and "gymnasium cannot make it" in r.err, r.err


def test_the_right_name_still_runs(bundle, cli):
    r = cli("eval", "b", "--env", "my_envs:make", *QUICK)
    assert r.code == 0, r.err


def test_an_observation_the_bundle_cannot_take_is_refused_before_any_rollout(bundle, cli):
    r = cli("eval", "b", "--env", "my_envs:make_dict", *QUICK)
    assert r.code == 2 and "observations are dicts" in r.err, r.err
    assert "eval:" not in r.err  # no condition started (the env's step would have failed the test)
