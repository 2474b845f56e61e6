"""MetaWorld through LeRobot's own environment (``lerobot.envs.metaworld.MetaworldEnv``) as a prop task:
the scripted experts' demonstrations, the user's variation, the image resize, the user's criterion.

Observations are what ``lerobot-eval --env.type=metaworld`` gives a policy: ``observation.image`` (the
``corner2`` camera, rendered 480 x 480 and flipped by LeRobot's env) and ``observation.state`` (4: hand
xyz and the gripper's opening, MetaWorld's ``agent_pos``); the action is 4-d in [-1, 1]. The policy sees
the image at ``IMAGE`` x ``IMAGE``, made from the 480 x 480 frame by ``resize_images`` (the resize the
prop LeRobot plugin applies at evaluation with ``--policy.resize_images=true``).

The base behaviour is the task as MetaWorld defines it, demonstrated by its own scripted policy
(``env.expert_policy``, which reads the full 39-d MetaWorld observation of the inner env). The user's
variation moves the task's goal by a fixed translation ``USER_OFFSET`` (10 cm up): the same scripted
policy, fed an observation whose object position is moved by the offset, drives the hand to the moved
goal (for button-press-topdown: it holds the hand 10 cm above the button instead of pressing it). The
user's criterion (``user_success``): the hand ends within ``USER_THRESHOLD`` (5 cm, MetaWorld's own
reach threshold) of the object's starting position moved by the offset.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("MUJOCO_GL", "egl")

IMAGE = 64  # the policy's camera resolution: ResNet-18 at 64 x 64 trains in minutes on 2 CPU cores
RENDER = 480  # what LeRobot's MetaworldEnv renders (MetaWorld's default; lerobot-eval cannot change it)
FPS = 80  # LeRobot's MetaWorld config
STATE, IMAGE_KEY, ACTION = "observation.state", "observation.image", "action"
USER_OFFSET = np.array([0.0, 0.0, 0.10])  # button-press-topdown: the task's goal moved 10 cm up
USER_THRESHOLD = 0.05  # MetaWorld's reach-v3 success distance (m)
# The user's variation per task: (offset of the object the expert acts on, the coordinates the user's
# criterion compares). handle-press-v3's expert aims 0.5 m below the handle, so moving it up still
# presses it: the user's handle is moved 10 cm along x instead and the hand, pressing down onto the
# table there, is judged in the table's plane (its height is wherever the table stops it).
# drawer-close-v3: the user wants the drawer left open: the handle moved 10 cm toward the robot, the
# expert parks the hand in front of it (at the height it approaches from), judged in the table's plane.
VARIATIONS = {
    "button-press-topdown-v3": (USER_OFFSET, (0, 1, 2)),
    "handle-press-v3": (np.array([0.10, 0.0, 0.0]), (0, 1)),
    "drawer-close-v3": (np.array([0.0, -0.10, 0.0]), (0, 1)),
}
# Judge horizon: the scripted experts finish these tasks in 35-92 steps (LeRobot's env would run 500).
HORIZON = 100
USER_HORIZON = 100  # frames recorded per user episode (the expert holds the moved goal after ~60)
NOISE = 0.1  # N(0, NOISE) added to the executed action while recording (the recorded one is clean)
# The tasks where the object the expert acts on is large in the camera image and moves from episode to
# episode, and MetaWorld's expert succeeds within ~80 steps (examples/RESULTS.md says how chosen).
TASKS = ("button-press-topdown-v3", "handle-press-v3", "drawer-close-v3")
# Slots of MetaWorld's 39-d observation that hold object positions (current frame, previous frame):
# moved by the offset for the user's expert. The hand (0:3, 18:21) and the gripper stay.
OBJECT_SLOTS = (slice(4, 7), slice(11, 14), slice(22, 25), slice(29, 32), slice(36, 39))


def features() -> dict:
    return {
        STATE: {"dtype": "float32", "shape": (4,), "names": ["x", "y", "z", "gripper"]},
        IMAGE_KEY: {"dtype": "image", "shape": (IMAGE, IMAGE, 3), "names": ["height", "width", "channels"]},
        ACTION: {"dtype": "float32", "shape": (4,), "names": ["dx", "dy", "dz", "grip"]},
    }


def resize_images(x: torch.Tensor, size: tuple[int, int] = (IMAGE, IMAGE)) -> torch.Tensor:
    """Float CHW (or NCHW) in [0, 1] -> the same at ``size``: bilinear with antialiasing
    (``F.interpolate(..., mode="bilinear", antialias=True, align_corners=False)``), the resize the prop
    LeRobot plugin applies at evaluation (``--policy.resize_images=true``): its own function where it
    is installed."""
    try:
        from lerobot_policy_prop.modeling_prop import resize_frames
    except ImportError:  # the same definition
        single = x.dim() == 3
        y = torch.nn.functional.interpolate(
            x[None] if single else x, size=size, mode="bilinear", antialias=True, align_corners=False
        )
        return y[0] if single else y
    return resize_frames(x, size)


def frame(pixels: np.ndarray) -> torch.Tensor:
    """LeRobot's env frame (HWC uint8, 480 x 480) -> float CHW in [0, 1] at IMAGE x IMAGE."""
    x = torch.from_numpy(np.ascontiguousarray(pixels)).permute(2, 0, 1).float() / 255.0
    return resize_images(x)


def to_uint8_hwc(x: torch.Tensor) -> np.ndarray:
    """How a frame is stored in the dataset (PNG): rounded to 1/255."""
    return (x.clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()


def moved(raw: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """MetaWorld's observation with every object position (and the goal) moved by ``offset``; slots
    that are padding (all zero) stay."""
    out = np.array(raw, dtype=np.float64, copy=True)
    for s in OBJECT_SLOTS:
        if np.any(out[s] != 0):
            out[s] += offset
    return out


class Env:
    """LeRobot's MetaworldEnv for one task, with the inner env's raw observation kept (the scripted
    policy reads it) and the object's starting position (the user's criterion)."""

    def __init__(self, task: str) -> None:
        from lerobot.envs.metaworld import MetaworldEnv

        self.task = task
        self.env = MetaworldEnv(task=task, obs_type="pixels_agent_pos")
        self.description = self.env.task_description
        self.raw: np.ndarray | None = None
        self.object0: np.ndarray | None = None

    def _capture(self) -> None:
        inner = self.env._env
        if getattr(inner, "_prop_captured", False):
            return
        step, reset = inner.step, inner.reset

        def step_(action):
            out = step(action)
            self.raw = np.asarray(out[0], np.float64).copy()
            return out

        def reset_(*a, **k):
            out = reset(*a, **k)
            self.raw = np.asarray(out[0], np.float64).copy()
            return out

        inner.step, inner.reset, inner._prop_captured = step_, reset_, True

    def reset(self, seed: int) -> dict:
        self.env._ensure_env()
        self._capture()
        obs, _ = self.env.reset(seed=seed)
        self.object0 = self.raw[4:7].copy()
        return obs

    def step(self, action: np.ndarray):
        """LeRobot's step (its env resets itself after a success, once the observation is taken)."""
        return self.env.step(np.asarray(action, np.float32))

    def expert(self, offset: np.ndarray | None = None) -> np.ndarray:
        raw = self.raw if offset is None else moved(self.raw, offset)
        return np.clip(self.env.expert_policy.get_action(raw), -1, 1).astype(np.float32)

    def close(self) -> None:
        self.env.close()


def hand(obs: dict) -> np.ndarray:
    return np.asarray(obs["agent_pos"][:3], np.float64)


def user_offset(task: str) -> np.ndarray:
    if task not in VARIATIONS:
        have = ", ".join(VARIATIONS)
        raise SystemExit(f"examples.metaworld: no user variation for {task} (these have one: {have})")
    return VARIATIONS[task][0]


def user_target(object0: np.ndarray, task: str = TASKS[0]) -> np.ndarray:
    return np.asarray(object0, np.float64) + user_offset(task)


def user_distance(final_hand: np.ndarray, object0: np.ndarray, task: str = TASKS[0]) -> float:
    """The hand's distance to the user's target over the task's criterion coordinates."""
    axes = list(VARIATIONS[task][1])
    return float(np.linalg.norm((np.asarray(final_hand) - user_target(object0, task))[axes]))


def user_success(final_hand: np.ndarray, object0: np.ndarray, task: str = TASKS[0]) -> bool:
    """The user's criterion: the hand ends within USER_THRESHOLD of the object's start moved by the
    task's offset (over the task's criterion coordinates)."""
    return user_distance(final_hand, object0, task) < USER_THRESHOLD


def record(
    root: Path, task: str, episodes: int, seed0: int, offset: np.ndarray | None = None,
    horizon: int | None = None, noise: float = NOISE,
) -> dict:  # fmt: skip
    """Scripted-expert episodes of ``task`` into a new LeRobotDataset at ``root``: LeRobot's env renders
    the frame, ``frame`` resizes it, the recorded action is the expert's clean one and the executed one
    carries N(0, noise) (DART: states off the expert's path get recorded too). ``offset`` None: the task
    as MetaWorld defines it, each episode ending on MetaWorld's success (or ``horizon``, default
    HORIZON); else the user's variation (the expert fed the moved object), ``horizon`` frames (default
    USER_HORIZON). Episode seeds are seed0, seed0 + 1, ...; returns counts (episodes, frames, base
    successes, user successes)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    horizon = horizon or (HORIZON if offset is None else USER_HORIZON)
    ds = LeRobotDataset.create(
        repo_id=f"local/{root.name}", fps=FPS, features=features(), root=root, robot_type="sawyer",
        use_videos=False, video_backend="pyav",
    )  # fmt: skip
    env = Env(task)
    rng = np.random.default_rng(seed0)
    counts = {"episodes": 0, "frames": 0, "success": 0, "user_success": 0, "steps": []}
    for ep in range(episodes):
        obs = env.reset(seed0 + ep)
        object0, success, steps = env.object0.copy(), False, 0
        while steps < horizon:
            steps += 1
            a = env.expert(offset)
            ds.add_frame({
                STATE: np.asarray(obs["agent_pos"], np.float32),
                IMAGE_KEY: to_uint8_hwc(frame(obs["pixels"])), ACTION: a, "task": env.description,
            })  # fmt: skip
            executed = np.clip(a + noise * rng.standard_normal(4).astype(np.float32), -1, 1)
            obs, _, terminated, _, info = env.step(executed)
            if info.get("is_success"):
                success = True
            if terminated and offset is None:
                break
        ds.save_episode()
        counts["episodes"] += 1
        counts["frames"] += steps
        counts["steps"].append(steps)
        counts["success"] += int(success)
        counts["user_success"] += int(user_success(hand(obs), object0, task))
    ds.finalize()
    env.close()
    return counts
