"""SB3 VecNormalize statistics: read without running the pickle, applied as SB3 applies them."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest

from prop_adapters.sb3.vecnormalize import read_vecnormalize
from prop_cli.errors import PropError
from tests.conftest import FAST

pytest.importorskip("stable_baselines3")


def _saved_vecnormalize(path, env_id="Pendulum-v1", steps=40, **kwargs):
    """A VecNormalize'd env stepped so its statistics move, saved with SB3's own VecNormalize.save."""
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecNormalize

    venv = VecNormalize(make_vec_env(env_id, n_envs=1, seed=0), **kwargs)
    venv.reset()
    for _ in range(steps):
        venv.step(np.array([venv.action_space.sample()]))
    venv.save(str(path))
    return venv


def test_statistics_equal_sb3s_load(tmp_path):
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecNormalize

    _saved_vecnormalize(tmp_path / "vn.pkl", clip_obs=2.0)
    ours = read_vecnormalize(tmp_path / "vn.pkl")
    truth = VecNormalize.load(str(tmp_path / "vn.pkl"), make_vec_env("Pendulum-v1", n_envs=1))
    obs = np.random.default_rng(0).normal(0, 4, (64, 3)).astype(np.float32)
    assert ours.keys is None and ours.clip_obs == 2.0
    np.testing.assert_array_equal(ours(obs), truth.normalize_obs(obs))
    assert np.abs(ours(obs)).max() == 2.0  # clipped


def test_dict_statistics_only_for_norm_obs_keys(tmp_path):
    import gymnasium as gym
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    class DictEnv(gym.Env):
        observation_space = gym.spaces.Dict(
            {"b": gym.spaces.Box(-5, 5, (2,)), "a": gym.spaces.Box(-5, 5, (3,))}
        )
        action_space = gym.spaces.Box(-1, 1, (1,))

        def reset(self, seed=None, options=None):
            super().reset(seed=seed)
            return self.observation_space.sample(), {}

        def step(self, a):
            return self.observation_space.sample(), 0.0, False, False, {}

    venv = VecNormalize(DummyVecEnv([DictEnv]), norm_obs_keys=["a"])
    venv.reset()
    for _ in range(20):
        venv.step(np.zeros((1, 1), np.float32))
    venv.save(str(tmp_path / "vn.pkl"))
    ours = read_vecnormalize(tmp_path / "vn.pkl")
    obs = DictEnv().observation_space.sample()
    got, want = ours(obs), venv.normalize_obs(obs)
    assert ours.keys == ["a"] and set(got) == {"a", "b"}
    np.testing.assert_array_equal(got["a"], want["a"])
    np.testing.assert_array_equal(got["b"], obs["b"])  # not in norm_obs_keys: untouched
    with pytest.raises(PropError, match="dict observations, the environment gives one array"):
        ours(obs["a"])


class _Hostile:
    """Pickles as a call of os.system that would write a marker file."""

    def __init__(self, marker) -> None:
        self.marker = marker

    def __reduce__(self):
        import os

        return (os.system, (f"touch {self.marker}",))


@pytest.mark.parametrize("wrap", ["bare", "inside_vecnormalize_state"])
def test_hostile_pickle_never_runs(tmp_path, cli, wrap):
    marker = tmp_path / "pwned"
    payload = _Hostile(marker)
    path = tmp_path / "evil.pkl"
    if wrap == "bare":
        path.write_bytes(pickle.dumps(payload))
    else:  # the call nested in state, as an attacker would hide it in obs_rms
        path.write_bytes(pickle.dumps({"clip_obs": 1.0, "obs_rms": payload}))
    with pytest.raises(PropError) as e:
        read_vecnormalize(path)
    assert "VecNormalize" in str(e.value) and not marker.exists()
    r = cli("eval", "nowhere.prop", "--env", "Pendulum-v1", "--vecnormalize", path)
    assert r.code == 2 and len(r.err.strip().splitlines()) == 1 and not marker.exists()


def test_object_arrays_and_broken_files_are_one_line_errors(tmp_path):
    (tmp_path / "obj.pkl").write_bytes(pickle.dumps(np.array([object()], dtype=object)))
    with pytest.raises(PropError, match="object array"):
        read_vecnormalize(tmp_path / "obj.pkl")
    (tmp_path / "junk.pkl").write_bytes(b"\x80\x05not a pickle")
    with pytest.raises(PropError, match="not a VecNormalize pickle"):
        read_vecnormalize(tmp_path / "junk.pkl")
    (tmp_path / "arr.pkl").write_bytes(pickle.dumps(np.zeros(3)))
    with pytest.raises(PropError, match="not SB3's VecNormalize"):
        read_vecnormalize(tmp_path / "arr.pkl")
    with pytest.raises(PropError, match="does not exist"):
        read_vecnormalize(tmp_path / "none.pkl")


def test_eval_with_vecnormalize_acts_as_sb3_on_its_normalised_env(tmp_path, cli):
    """A PPO policy trained behind VecNormalize: prop's no-key actions on the env's raw observations,
    normalised by --vecnormalize's statistics, equal SB3's predict on VecNormalize.normalize_obs."""
    import gymnasium as gym
    from stable_baselines3 import PPO

    from prop_cli.bundle import load_bundle
    from prop_cli.run.policy import KeyedPolicy, array_observation

    venv = _saved_vecnormalize(tmp_path / "vn.pkl", clip_obs=3.0)
    venv.training = False
    model = PPO("MlpPolicy", venv, seed=0, device="cpu")
    model.save(tmp_path / "ppo.zip")
    rng = np.random.default_rng(0)
    x = venv.normalize_obs(rng.normal(0, 2, (64, 3)).astype(np.float32))
    np.savez(tmp_path / "mine.npz", x=x, y=rng.uniform(-1, 1, (64, 1)).astype(np.float32))
    (tmp_path / "k.bin").write_bytes(rng.integers(0, 256, 16, dtype=np.uint8).tobytes())
    r = cli("personalize", tmp_path / "ppo.zip", "--data", tmp_path / "mine.npz", "--key-file",
            tmp_path / "k.bin", "--out", tmp_path / "b", "--freeze-base", *FAST)  # fmt: skip
    assert r.code == 0, r.err
    bundle = load_bundle(tmp_path / "b")
    prepare = array_observation(bundle, read_vecnormalize(tmp_path / "vn.pkl"))
    ours = KeyedPolicy(bundle)
    env = gym.make("Pendulum-v1")
    obs, _ = env.reset(seed=3)
    worst = 0.0
    for _ in range(30):
        a, _ = ours.predict(prepare(obs))
        want, _ = model.predict(venv.normalize_obs(obs), deterministic=True)
        worst = max(worst, float(np.abs(a - want).max()))
        obs, *_ = env.step(a)
    assert worst < 1e-5
    quick = ["--episodes", "2", "--max-steps", "5", "--random-keys", "1", "--episodes-per-key", "1", "--json"]
    args = ["eval", tmp_path / "b", "--env", "Pendulum-v1", *quick]
    normalised = cli(*args, "--vecnormalize", tmp_path / "vn.pkl")
    assert normalised.code == 0, normalised.err
    assert json.loads(normalised.out) != json.loads(cli(*args).out)  # the statistics are applied
