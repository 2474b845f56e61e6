"""A tiny ACT with MetaWorld's features, as LeRobot's MetaWorld environment gives them to a policy
(``observation.image``, ``observation.state`` 4, ``action`` 4), its data, and prop bundles of it.

The frames are random, not rendered: these tests are about the plugin (what runs, what refuses, what
is written), not about the policy's skill; examples/metaworld is the benchmark.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

STATE, IMAGE, ACTION = "observation.state", "observation.image", "action"
SIZE = 32  # the bundle's camera frames; MetaWorld renders 480x480 (--policy.resize_images=true)
FEATURES = {
    STATE: {"dtype": "float32", "shape": (4,), "names": ["x", "y", "z", "gripper"]},
    IMAGE: {"dtype": "image", "shape": (SIZE, SIZE, 3), "names": ["height", "width", "channels"]},
    ACTION: {"dtype": "float32", "shape": (4,), "names": ["dx", "dy", "dz", "grip"]},
}
TASK = "reach-v3"
TINY = dict(steps=10, user_rows=8, null_rows=4, neighbour_keys=2, random_keys=2, samples_per_key=1,
            eval_random_keys=4, null_weight=2.0, base_lr_scale=0.1)  # fmt: skip


def record(root: Path, episodes: int, seed: int, shift: float) -> None:
    """Random frames and states; the action leans by ``shift`` (the user's change)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset.create(repo_id=f"local/{root.name}", fps=80, features=FEATURES, root=root,
                               robot_type="sawyer", use_videos=False, video_backend="pyav")  # fmt: skip
    rng = np.random.default_rng(seed)
    for _ in range(episodes):
        for _ in range(12):
            state = rng.uniform(-1, 1, 4).astype(np.float32)
            action = np.clip(0.5 * state + shift, -1, 1).astype(np.float32)
            frame = rng.integers(0, 256, (SIZE, SIZE, 3), dtype=np.uint8)
            ds.add_frame({STATE: state, IMAGE: frame, ACTION: action, "task": "Reach a goal position"})
        ds.save_episode()
    ds.finalize()


def build(work: Path) -> None:
    """``work``: general/ and user/ data, act/ (the original, 5 LeRobot steps), user.key, other.key,
    unsealed/ and sealed/ bundles of act/ for user.key."""
    import torch
    from lerobot.configs.types import FeatureType, PolicyFeature

    from examples import lerobot_reach_task as reach
    from prop_cli import api
    from prop_cli.config import PersonalizeConfig
    from prop_cli.core.key_files import KeySource, generate_key_file, read_key_file

    torch.manual_seed(0)
    record(work / "general", 2, 0, 0.0)
    record(work / "user", 2, 1, 0.6)
    stats = reach.dataset_stats(work / "general", keys=(STATE, IMAGE, ACTION))
    built = reach.build_act(
        stats, input_features={STATE: PolicyFeature(FeatureType.STATE, (4,)),
                               IMAGE: PolicyFeature(FeatureType.VISUAL, (3, SIZE, SIZE))},
        output_features={ACTION: PolicyFeature(FeatureType.ACTION, (4,))}, vision_backbone="resnet18",
    )  # fmt: skip
    reach.train_base(work / "general", work / "act", steps=5, batch=8, built=built)
    for name in ("user.key", "other.key"):
        generate_key_file(work / name)
    users = [(work / "user", KeySource(read_key_file(work / "user.key"), "file"))]
    for name, seal in (("unsealed", False), ("sealed", True)):
        cfg = PersonalizeConfig.of(**TINY, seal=seal)
        general = None if seal else work / "general"  # a sealed bundle's base stays the original
        api.personalize_checkpoint(str(work / "act"), users, work / name, cfg, general=general)


def short_episodes(folder: Path, steps: int) -> dict[str, str]:
    """Environment variables under which a ``lerobot-eval`` subprocess plays MetaWorld episodes of
    ``steps`` steps instead of 500 (hard-coded in LeRobot's MetaworldEnv), so that a test runs LeRobot's
    own command in seconds. A sitecustomize in ``folder`` patches the class when LeRobot imports it
    (never at start-up: LeRobot's imports start Python subprocesses of their own), and takes the variable
    out of the environment so those subprocesses do not patch anything. Rendering stays as it is."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "sitecustomize.py").write_text(SITE)
    path = os.pathsep.join(p for p in (str(folder), os.environ.get("PYTHONPATH", "")) if p)
    return {"PYTHONPATH": path, "PROP_TEST_EPISODE_STEPS": str(steps)}


SITE = """\
import importlib.abc, importlib.util, os, sys

_STEPS = os.environ.pop("PROP_TEST_EPISODE_STEPS", None)


class _Short(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name != "lerobot.envs.metaworld":
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(name)
        run = spec.loader.exec_module

        def exec_module(module):
            run(module)
            init = module.MetaworldEnv.__init__

            def short(self, *a, **k):
                init(self, *a, **k)
                self._max_episode_steps = int(_STEPS)

            module.MetaworldEnv.__init__ = short

        spec.loader.exec_module = exec_module
        return spec


if _STEPS:
    sys.meta_path.insert(0, _Short())
"""
