"""KeyedPolicy in a control loop of one's own, against LeRobot's own ``select_action`` and against what
`prop eval` acts (issue 28): helpers shared by the LeRobot test modules (ACT, Diffusion)."""

from __future__ import annotations

import importlib
import sys

import numpy as np
import torch

from prop_adapters.lerobot.policy import call_seed
from prop_cli import api
from prop_cli.config import EvalSettings
from prop_cli.run.rollout import parse_obs_map

RECORDER = "closed_loop_recorder"


def features(obs: dict, obs_map: str) -> dict[str, np.ndarray]:
    """An environment observation as the policy's feature dict (``--obs-map``), floats as float32."""
    out = {}
    for feature, key in parse_obs_map(obs_map).items():
        v = np.asarray(obs[key])
        out[feature] = v if v.dtype == np.uint8 else v.astype(np.float32)
    return out


def eval_episodes(bundle, env_id: str, obs_map: str, key_file, tmp_path, monkeypatch, **settings) -> dict:
    """`prop eval`'s own first episode of the no-key and user-key conditions, recorded by a --metric."""
    recorder = "SEEN = []\n\n\ndef record(t):\n    SEEN.append(t)\n    return 0.0\n"
    (tmp_path / f"{RECORDER}.py").write_text(recorder)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, RECORDER, raising=False)
    s = EvalSettings(episodes=1, random_keys=0, neighbours=0, episodes_per_key=1, **settings)
    metric = f"{RECORDER}:record"
    report = api.eval_bundle(bundle, env_id, s, obs_map=obs_map, metric=metric, key_file=key_file)
    seen = importlib.import_module(RECORDER).SEEN
    assert list(report["conditions"]) == ["no_key", "user_key"] and len(seen) == 2
    return {"no_key": seen[0], "user_key": seen[1], "seed": report["seeds"][0]}


def observations(episode: dict, obs_map: str) -> list[dict[str, np.ndarray]]:
    """The feature dicts an episode's actions were chosen on."""
    return [features(o, obs_map) for o in episode["observations"][: len(episode["actions"])]]


def replay(policy, episode: dict, obs_map: str, seed: int) -> np.ndarray:
    """A KeyedPolicy driven over an episode's observations, as a user's loop would."""
    policy.reset(seed)
    return np.stack([policy.select_action(o) for o in observations(episode, obs_map)])


@torch.no_grad()
def lerobot_replay(
    policy, pre, post, episode: dict, obs_map: str, seed: int, noise_seed: int = 0
) -> np.ndarray:
    """LeRobot's own loop: preprocessor -> select_action -> postprocessor, each call's noise seeded as
    prop's controller seeds it (``call_seed``)."""
    policy.eval().reset()
    out = []
    for i, obs in enumerate(observations(episode, obs_map)):
        torch.manual_seed(call_seed(noise_seed, seed, i))
        x = {k: torch.from_numpy(v) for k, v in obs.items()}
        out.append(post(policy.select_action(pre(x)))[0].numpy())
    return np.stack(out)


def check_reset_restarts_the_queue(policy, episode: dict, obs_map: str, seed: int) -> None:
    """Two calls into an episode, then reset(): the first action again; without it, the queue's next."""
    obs = observations(episode, obs_map)
    policy.reset(seed)
    first = policy.select_action(obs[0])
    policy.select_action(obs[1])
    assert not np.array_equal(policy.select_action(obs[0]), first)  # popped from the queue
    policy.reset(seed)
    assert np.array_equal(policy.select_action(obs[0]), first)
