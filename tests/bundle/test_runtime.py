"""KeyedPolicy: a key folded once, then SB3-style predict (issue 10, fix 3)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from prop_cli.api import KeyedPolicy, KeySource, load_bundle, personalize_checkpoint, run_bundle
from prop_cli.config import PersonalizeConfig
from prop_cli.core.key_files import read_key_file
from prop_cli.errors import PropError
from tests.adapters.test_sb3 import make_zip, sb3_state


@pytest.fixture(scope="module")
def bundles(tmp_path_factory):
    d = tmp_path_factory.mktemp("policy")
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (80, 3)).astype(np.float32)
    (d / "k.bin").write_bytes(rng.integers(0, 256, 16, dtype=np.uint8).tobytes())
    (d / "k.bin").chmod(0o600)
    key = KeySource(read_key_file(d / "k.bin"), "file")
    np.savez(d / "box.npz", x=x, y=np.clip(-x[:, :2], -2, 2).astype(np.float32))
    np.savez(d / "discrete.npz", x=x, y=(x[:, 0] > 0).astype(np.int64) * 3)
    cfg = PersonalizeConfig.of(steps=30)
    for name, data, kw in (
        ("ppo", "box.npz", {}),
        ("cartpole", "discrete.npz", {"discrete": True, "act": 4}),
    ):
        make_zip(d / f"{name}.zip", state=sb3_state("actor_critic", **kw), **kw)
        personalize_checkpoint(str(d / f"{name}.zip"), [(d / data, key)], d / f"{name}.prop", cfg)
    return d, key.bits


def test_fold_happens_once_not_per_call(bundles):
    d, key = bundles
    b = load_bundle(d / "ppo.prop")
    calls = []
    b.keyed.encoder.register_forward_hook(lambda *a: calls.append(1))
    policy = KeyedPolicy(b, key)
    obs = np.zeros((1, 3), np.float32)
    for _ in range(50):
        policy.predict(obs)[0]
    assert len(calls) == 1  # the encoder ran once, at construction
    run_bundle(b, obs, key)
    assert len(calls) == 2


def test_predict_like_sb3_single_batch_and_clipped(bundles):
    d, key = bundles
    b = load_bundle(d / "ppo.prop")
    policy = KeyedPolicy(b, key)
    obs = np.random.default_rng(1).uniform(-1, 1, (16, 3)).astype(np.float32)
    raw = policy(obs * 50)  # far outside the data: the Gaussian mean leaves the bounds
    act, state = policy.predict(obs * 50, state=None, episode_start=None, deterministic=True)
    assert state is None
    np.testing.assert_array_equal(act, np.clip(raw, -2, 2))  # PPO predict clips to the Box
    assert policy.predict(obs[0])[0].shape == (2,)  # one observation in, one action out
    np.testing.assert_allclose(policy.predict(obs[0])[0], policy.predict(obs)[0][0], rtol=1e-6)
    np.testing.assert_allclose(KeyedPolicy(b)(obs), b.keyed.module(torch.from_numpy(obs)).detach().numpy())


def test_predict_discrete_gives_the_argmax(bundles):
    d, key = bundles
    policy = KeyedPolicy(load_bundle(d / "cartpole.prop"), key)
    obs = np.random.default_rng(2).uniform(-1, 1, (8, 3)).astype(np.float32)
    np.testing.assert_array_equal(policy.predict(obs)[0], policy(obs).argmax(-1))
    assert policy.predict(obs[0])[0].shape == ()
    with pytest.raises(PropError, match="deterministic=True"):
        policy.predict(obs, deterministic=False)


def test_a_dict_for_an_array_bundle_is_one_line_and_the_loop_api_is_shared(bundles):
    """LeRobot's observation dict given to an array model: one PropError line naming the shape it takes
    (issue 28). select_action and reset, the LeRobot loop's names, work on array models too."""
    d, key = bundles
    policy = KeyedPolicy(load_bundle(d / "ppo.prop"), key)
    obs = np.random.default_rng(4).uniform(-1, 1, 3).astype(np.float32)
    for call in (policy.predict, policy.select_action, policy):
        with pytest.raises(PropError, match=r"shape \(3,\), not a dict \(keys observation.state\)") as e:
            call({"observation.state": obs})
        assert "\n" not in str(e.value)
    policy.reset(0)  # feed-forward: nothing to reset
    np.testing.assert_array_equal(policy.select_action(obs), policy.predict(obs)[0])


def test_predict_drives_a_gymnasium_loop_the_sb3_way(tmp_path):
    gym = pytest.importorskip("gymnasium")
    rng = np.random.default_rng(3)
    x = rng.uniform(-1, 1, (60, 3)).astype(np.float32)
    np.savez(tmp_path / "d.npz", x=x, y=np.clip(x[:, :1], -2, 2).astype(np.float32))
    make_zip(tmp_path / "pendulum.zip", state=sb3_state("actor_critic", act=1), act=1)
    key = KeySource(rng.integers(0, 2, 128).astype(np.uint8), "file")
    cfg = PersonalizeConfig.of(steps=5)
    personalize_checkpoint(str(tmp_path / "pendulum.zip"), [(tmp_path / "d.npz", key)], tmp_path / "b", cfg)
    policy = KeyedPolicy(load_bundle(tmp_path / "b"), key.bits)
    env = gym.make("Pendulum-v1")
    obs, _ = env.reset(seed=0)
    state, episode_start = None, np.ones((1,), bool)
    for _ in range(20):
        action, state = policy.predict(obs, state=state, episode_start=episode_start, deterministic=True)
        assert env.action_space.contains(action.astype(np.float32))
        obs, reward, terminated, truncated, _ = env.step(action)
        episode_start = np.array([terminated or truncated])
    env.close()
