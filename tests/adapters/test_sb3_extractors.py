"""SB3 MultiInputPolicy (Dict observations) and CnnPolicy: prop's actor equals SB3's predict."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from prop_adapters import load_checkpoint
from prop_adapters.sb3.adapter import observation_array

# Image inputs make a step ~20x a tiny MLP's (conftest's FAST: 40 steps); these checks need a bundle,
# not a fit.
IMAGE_STEPS = ["--steps", "10", "--device", "cpu"]

pytest.importorskip("stable_baselines3")
gym = pytest.importorskip("gymnasium")


class ImageEnv(gym.Env):
    """A uint8 HWC image observation (SB3 wraps it in VecTransposeImage), optionally in a Dict."""

    def __init__(self, as_dict: bool = False, discrete: bool = True) -> None:
        image = gym.spaces.Box(0, 255, (36, 36, 3), np.uint8)
        self.observation_space = (
            gym.spaces.Dict({"state": gym.spaces.Box(-1, 1, (4,)), "camera": image}) if as_dict else image
        )
        self.action_space = gym.spaces.Discrete(3) if discrete else gym.spaces.Box(-1, 1, (2,))

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, a):
        return self.observation_space.sample(), 0.0, False, False, {}


def _actions_match(model, path: Path, observations) -> float:
    """max |prop's action - SB3's predict(obs, deterministic=True)| over ``observations`` (raw env obs)."""
    loaded = load_checkpoint(path)
    worst = 0.0
    for obs in observations:
        want, _ = model.predict(obs, deterministic=True)
        with torch.no_grad():
            y = loaded.module(torch.from_numpy(observation_array(loaded.spec, obs))[None]).numpy()[0]
        got = y.argmax() if loaded.continuous is False else np.clip(y, loaded.action_low, loaded.action_high)
        worst = max(worst, float(np.abs(np.asarray(got, np.float64) - want).max()))
    return worst


@pytest.mark.parametrize("algo", ["PPO", "SAC"])
def test_multi_input_policy_with_an_image_key_equals_predict(tmp_path, algo):
    import stable_baselines3 as sb3

    env = ImageEnv(as_dict=True, discrete=algo == "PPO")
    kwargs = {"buffer_size": 10} if algo == "SAC" else {"n_steps": 8, "batch_size": 8}
    model = getattr(sb3, algo)("MultiInputPolicy", env, seed=0, device="cpu", **kwargs)
    model.save(tmp_path / "m.zip")
    env.reset(seed=0)
    assert (
        _actions_match(model, tmp_path / "m.zip", [env.observation_space.sample() for _ in range(8)]) < 1e-5
    )
    loaded = load_checkpoint(tmp_path / "m.zip")
    # gymnasium sorts Dict keys: camera (3*36*36) first, then state (4).
    assert [k["key"] for k in loaded.spec["observation_keys"]] == ["camera", "state"]
    assert loaded.input_shape == (3 * 36 * 36 + 4,)


def test_panda_reach_multi_input_policy_equals_predict(tmp_path):
    pytest.importorskip("panda_gym")
    from stable_baselines3 import PPO

    from prop_cli.run.rollout import make_env

    env = make_env("panda_gym:PandaReach-v3")
    model = PPO("MultiInputPolicy", env, seed=0, device="cpu", n_steps=8, batch_size=8)
    model.save(tmp_path / "reach.zip")
    obs, _ = env.reset(seed=0)
    observations = []
    for _ in range(10):
        observations.append(obs)
        obs, *_ = env.step(env.action_space.sample())
    env.close()
    assert _actions_match(model, tmp_path / "reach.zip", observations) < 1e-5
    spec = load_checkpoint(tmp_path / "reach.zip").spec
    assert [k["key"] for k in spec["observation_keys"]] == ["achieved_goal", "desired_goal", "observation"]


def test_cnn_policy_equals_predict_and_personalizes(tmp_path, cli):
    from stable_baselines3 import PPO

    env = ImageEnv()
    kw = {"features_extractor_kwargs": {"features_dim": 32}}
    model = PPO("CnnPolicy", env, seed=0, device="cpu", n_steps=8, batch_size=8, policy_kwargs=kw)
    model.save(tmp_path / "cnn.zip")
    env.reset(seed=0)
    assert (
        _actions_match(model, tmp_path / "cnn.zip", [env.observation_space.sample() for _ in range(8)]) == 0
    )
    r = cli("inspect", tmp_path / "cnn.zip", "--json")
    assert r.code == 0, r.err
    info = json.loads(r.out)
    assert info["model"]["extractor"] == "cnn" and info["model"]["observation_shape"] == [3, 36, 36]

    # The data's x are CHW images (raw 0..255 values), y discrete actions.
    rng = np.random.default_rng(0)
    x = rng.integers(0, 256, (24, 3, 36, 36)).astype(np.float32)
    np.savez(tmp_path / "mine.npz", x=x, y=rng.integers(0, 3, 24))
    (tmp_path / "k.bin").write_bytes(rng.integers(0, 256, 16, dtype=np.uint8).tobytes())
    r = cli("personalize", tmp_path / "cnn.zip", "--data", tmp_path / "mine.npz", "--key-file",
            tmp_path / "k.bin", "--out", tmp_path / "b", *IMAGE_STEPS)  # fmt: skip
    assert r.code == 0, r.err
    manifest = json.loads((tmp_path / "b" / "manifest.json").read_text())
    assert [entry["name"] for entry in manifest["keyed_layers"]] == [
        "features_extractor.linear.0",
        "action_net",
    ]

    # The base file loads into SB3 (features extractor aliases written from the fine-tuned module) and
    # SB3's logits on it equal the bundle's no-key outputs.
    from prop_cli.bundle import load_bundle
    from prop_cli.run.policy import KeyedPolicy

    base = load_file(str(tmp_path / "b" / "base.safetensors"))
    assert set(base) == set(model.policy.state_dict())
    model.policy.load_state_dict(base)
    for alias in ("pi_features_extractor", "vf_features_extractor"):
        assert torch.equal(base[f"{alias}.linear.0.weight"], base["features_extractor.linear.0.weight"])
    ours = KeyedPolicy(load_bundle(tmp_path / "b"))
    obs = torch.from_numpy(x[:6])
    with torch.no_grad():
        sb3_logits = model.policy.get_distribution(obs).distribution.logits
        ours_logits = torch.log_softmax(torch.from_numpy(ours(x[:6])), -1)
    assert torch.allclose(sb3_logits, ours_logits, atol=1e-5)


def test_frozen_base_cnn_bundle_without_key_is_the_original(tmp_path, cli):
    from stable_baselines3 import PPO

    from prop_cli.bundle import load_bundle
    from prop_cli.run.policy import KeyedPolicy

    env = ImageEnv(discrete=False)
    kw = {"features_extractor_kwargs": {"features_dim": 16}}
    model = PPO("CnnPolicy", env, seed=1, device="cpu", n_steps=8, batch_size=8, policy_kwargs=kw)
    model.save(tmp_path / "cnn.zip")
    rng = np.random.default_rng(1)
    x = rng.integers(0, 256, (16, 3, 36, 36)).astype(np.float32)
    np.savez(tmp_path / "mine.npz", x=x, y=rng.uniform(-1, 1, (16, 2)).astype(np.float32))
    (tmp_path / "k.bin").write_bytes(rng.integers(0, 256, 16, dtype=np.uint8).tobytes())
    r = cli("personalize", tmp_path / "cnn.zip", "--data", tmp_path / "mine.npz", "--key-file",
            tmp_path / "k.bin", "--out", tmp_path / "b", "--freeze-base", *IMAGE_STEPS)  # fmt: skip
    assert r.code == 0, r.err
    ours = KeyedPolicy(load_bundle(tmp_path / "b"))
    hwc = np.moveaxis(x[:5], 1, -1).astype(np.uint8)
    for img in hwc:
        want, _ = model.predict(img, deterministic=True)
        got, _ = ours.predict(observation_array(ours_spec(tmp_path / "b"), img))
        np.testing.assert_allclose(got, want, atol=1e-5)


def ours_spec(bundle: Path) -> dict:
    return json.loads((bundle / "manifest.json").read_text())["model"]
