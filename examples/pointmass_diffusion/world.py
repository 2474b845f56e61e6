"""What the tasks of examples/pointmass_diffusion share: the square world a velocity command moves a point
in, the camera image, and recording / rolling out any task (a module defining ``Env``, ``expert``,
``outcome``, ``features`` and its constants; see task.py, task_waypoint.py, task_slow.py).

A task module defines: ``NAME``, ``DESCRIPTION`` (LeRobot's task string), ``FPS``, ``HORIZON``,
``THRESHOLD`` (success: the final distance to the goal under it), ``USER_CHANGE`` (the user's change in
words), ``USER_BY_DISTANCE`` (whether the user's criterion is ``user_distance`` under a threshold, so
``table --threshold`` re-reads it too), ``features()``, ``Env(seeds)`` (``observation()``, ``step(a)``),
``expert(env, user)`` (the base or the user's clean action) and ``outcome(env)`` (per episode: seed,
success, user, distance, user_distance, lean: how far the episode went toward the user's change)."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType

import numpy as np

SPEED = 0.1  # a full-speed step moves the point this far
NOISE = 0.3  # DART: N(0, NOISE) on the executed action while recording
IMAGE = 16
SIGMA = 0.7  # blob radius, pixels
STATE, IMAGE_KEY, ACTION = "observation.state", "observation.image", "action"
TASKS = {
    "reach": "examples.pointmass_diffusion.task",
    "waypoint": "examples.pointmass_diffusion.task_waypoint",
    "slow": "examples.pointmass_diffusion.task_slow",
}


def load(name: str) -> ModuleType:
    import importlib

    return importlib.import_module(TASKS[name])


def state_feature() -> dict:
    return {STATE: {"dtype": "float32", "shape": (4,), "names": ["x", "y", "goal_x", "goal_y"]}}


def image_feature() -> dict:
    names = ["height", "width", "channels"]
    return {IMAGE_KEY: {"dtype": "image", "shape": (IMAGE, IMAGE, 3), "names": names}}


def action_feature() -> dict:
    return {ACTION: {"dtype": "float32", "shape": (2,), "names": ["vx", "vy"]}}


def _blob(pos: np.ndarray) -> np.ndarray:
    """(N, 2) positions in [-1, 1] -> (N, IMAGE, IMAGE) Gaussian blobs, peak 1 (row = y, col = x)."""
    grid = np.arange(IMAGE, dtype=np.float64)
    px = (pos + 1) / 2 * (IMAGE - 1)
    gx = np.exp(-((grid[None, :] - px[:, :1]) ** 2) / (2 * SIGMA**2))
    gy = np.exp(-((grid[None, :] - px[:, 1:]) ** 2) / (2 * SIGMA**2))
    return gy[:, :, None] * gx[:, None, :]


def render(position: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """(N, 2), (N, 2) -> (N, IMAGE, IMAGE, 3) uint8: the goal red, the point blue."""
    img = np.zeros((len(position), IMAGE, IMAGE, 3))
    img[..., 0] = _blob(goal)
    img[..., 2] = _blob(position)
    return np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)


class Square:
    """Every seed an episode, all stepped together (row i: seed ``seeds[i]``): the point starts uniform in
    [-0.8, 0.8]^2, the goal uniform in [-0.5, 0.5]^2 (both from the seed); an action in [-1, 1]^2 moves
    the point ``SPEED`` times it, kept in the square. ``path``: every position so far (the first the
    start). ``image``: whether the observation has the camera frame."""

    image = True

    def __init__(self, seeds: list[int]) -> None:
        self.seeds = list(seeds)
        starts = [np.random.default_rng((int(s), 43)).uniform(-1, 1, 4) for s in self.seeds]
        self.position = np.array([s[:2] * 0.8 for s in starts])
        self.goal = np.array([s[2:] * 0.5 for s in starts])
        self.path = [self.position]
        self.actions: list[np.ndarray] = []

    def observation(self) -> dict[str, np.ndarray]:
        state = np.concatenate([self.position, self.goal], 1).astype(np.float32)
        return {STATE: state, IMAGE_KEY: render(self.position, self.goal)} if self.image else {STATE: state}

    def step(self, action: np.ndarray) -> None:
        a = np.clip(np.asarray(action, np.float64).reshape(len(self.seeds), 2), -1, 1)
        self.actions.append(a)
        self.position = np.clip(self.position + SPEED * a, -1, 1)
        self.path.append(self.position)


def record(t: ModuleType, root: Path, episodes: int, seed0: int, user: bool, noise: float = NOISE) -> dict:
    """Task ``t``'s expert episodes (seeds seed0, seed0 + 1, ...; the user's if ``user``) into a new
    LeRobotDataset at ``root``, ``t.HORIZON`` frames each, N(0, ``noise``) on the executed action (DART),
    the clean action recorded; returns counts (episodes, frames, successes, user successes)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset.create(
        repo_id=f"local/{root.name}",
        fps=t.FPS,
        features=t.features(),
        root=root,
        robot_type="pointmass",
        use_videos=False,
    )
    rng = np.random.default_rng((seed0, 43, 1))
    env = t.Env([seed0 + i for i in range(episodes)])
    frames: list[list[dict]] = [[] for _ in range(episodes)]
    for _ in range(t.HORIZON):
        obs, a = env.observation(), t.expert(env, user)
        for i in range(episodes):
            frames[i].append({**{k: v[i] for k, v in obs.items()}, ACTION: a[i], "task": t.DESCRIPTION})
        env.step(a + noise * rng.standard_normal(a.shape))
    for ep in frames:
        for f in ep:
            ds.add_frame(f)
        ds.save_episode()
    ds.finalize()
    out = t.outcome(env)
    return {
        "episodes": episodes,
        "frames": episodes * t.HORIZON,
        "success": sum(o["success"] for o in out),
        "user_success": sum(o["user"] for o in out),
    }


def rollouts(t: ModuleType, controller, seeds: list[int], batch_seed: int = 0) -> list[dict]:
    """One episode of task ``t`` per seed, all as one batch through ``controller`` (prop's LeRobot
    Controller or a KeyedPolicy): the sampler's noise comes from ``batch_seed`` and the call's number, so
    every condition run on the same seeds draws the same noise (paired)."""
    env = t.Env(seeds)
    controller.reset(batch_seed)
    for _ in range(t.HORIZON):
        env.step(controller.select_action(env.observation()))
    return t.outcome(env)


def episodes(env: Square, success, user, distance, user_distance, lean) -> list[dict]:
    """A task's ``outcome``: per episode (arrays over ``env.seeds``) the seed, success and the user's
    criterion (0/1), the final distance to the goal, the user's measure and the lean (5 decimals)."""
    return [
        {
            "seed": s,
            "success": int(success[i]),
            "user": int(user[i]),
            "distance": round(float(distance[i]), 5),
            "user_distance": round(float(user_distance[i]), 5),
            "lean": round(float(lean[i]), 5),
        }
        for i, s in enumerate(env.seeds)
    ]
