"""A 2-D point-mass reaching task seen through a small rendered camera image plus its state (issue 43):
no simulator, numpy only, every episode a batch row (all of a condition's seeds step together).

- **World**: the square [-1, 1]^2. The point starts uniform in [-0.8, 0.8]^2, the goal uniform in
  [-0.5, 0.5]^2 (both from the episode's seed). The action is a velocity command in [-1, 1]^2; a step
  moves the point by ``SPEED`` times the clipped action, kept in the square.
- **Observation**: ``observation.image``, a ``IMAGE`` x ``IMAGE`` RGB frame (the goal a red blob, the
  point a blue one, Gaussian, on black), and ``observation.state`` = (x, y, goal x, goal y).
- **Expert**: ``clip(GAIN * (target - position), -1, 1)``: full speed, then an exponential approach.
  The base demonstrations go to the goal; the user's go to the goal moved by ``USER_OFFSET`` (the user's
  change: "stop 0.3 to the right of the goal"). Recorded with N(0, ``NOISE``) on the executed action
  (DART: off-path states get recorded too), the clean action recorded.
- **Success**: the final distance to the goal below ``THRESHOLD`` after ``HORIZON`` steps. The user's
  criterion: the final distance to the moved goal below ``THRESHOLD``. ``lean``: the final position's
  offset from the goal projected on the user's offset direction (how far an episode ends toward the
  user's goal; the original ends near 0, the user's key near 0.3).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

IMAGE = 16
FPS = 10
SPEED = 0.1
GAIN = 4.0
HORIZON = 30
THRESHOLD = 0.05
USER_OFFSET = np.array([0.3, 0.0])
NOISE = 0.3
STATE, IMAGE_KEY, ACTION = "observation.state", "observation.image", "action"
DESCRIPTION = "reach the red goal"
SIGMA = 0.7  # blob radius, pixels


def features() -> dict:
    return {
        STATE: {"dtype": "float32", "shape": (4,), "names": ["x", "y", "goal_x", "goal_y"]},
        IMAGE_KEY: {"dtype": "image", "shape": (IMAGE, IMAGE, 3), "names": ["height", "width", "channels"]},
        ACTION: {"dtype": "float32", "shape": (2,), "names": ["vx", "vy"]},
    }


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


class Env:
    """Every seed an episode, all stepped together (row i: seed ``seeds[i]``)."""

    def __init__(self, seeds: list[int]) -> None:
        self.seeds = list(seeds)
        starts = [np.random.default_rng((int(s), 43)).uniform(-1, 1, 4) for s in self.seeds]
        self.position = np.array([s[:2] * 0.8 for s in starts])
        self.goal = np.array([s[2:] * 0.5 for s in starts])

    def observation(self) -> dict[str, np.ndarray]:
        state = np.concatenate([self.position, self.goal], 1).astype(np.float32)
        return {STATE: state, IMAGE_KEY: render(self.position, self.goal)}

    def step(self, action: np.ndarray) -> None:
        a = np.clip(np.asarray(action, np.float64).reshape(len(self.seeds), 2), -1, 1)
        self.position = np.clip(self.position + SPEED * a, -1, 1)

    def expert(self, offset: np.ndarray | None = None) -> np.ndarray:
        target = self.goal + (0 if offset is None else offset)
        return np.clip(GAIN * (target - self.position), -1, 1).astype(np.float32)


def outcome(env: Env) -> list[dict]:
    """Per episode: success, the user's criterion, final distances, lean toward the user's offset."""
    d = np.linalg.norm(env.position - env.goal, axis=1)
    du = np.linalg.norm(env.position - env.goal - USER_OFFSET, axis=1)
    lean = (env.position - env.goal) @ (USER_OFFSET / np.linalg.norm(USER_OFFSET))
    return [
        {
            "seed": s,
            "success": int(d[i] < THRESHOLD),
            "user": int(du[i] < THRESHOLD),
            "distance": round(float(d[i]), 5),
            "user_distance": round(float(du[i]), 5),
            "lean": round(float(lean[i]), 5),
        }
        for i, s in enumerate(env.seeds)
    ]


def record(
    root: Path, episodes: int, seed0: int, offset: np.ndarray | None = None, noise: float = NOISE
) -> dict:
    """Expert episodes (seeds seed0, seed0 + 1, ...) into a new LeRobotDataset at ``root``, HORIZON
    frames each; returns counts (episodes, frames, successes, user successes of the executed runs)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset.create(
        repo_id=f"local/{root.name}",
        fps=FPS,
        features=features(),
        root=root,
        robot_type="pointmass",
        use_videos=False,
    )
    rng = np.random.default_rng((seed0, 43, 1))
    env = Env([seed0 + i for i in range(episodes)])
    frames: list[list[dict]] = [[] for _ in range(episodes)]
    for _ in range(HORIZON):
        obs, a = env.observation(), env.expert(offset)
        for i in range(episodes):
            frames[i].append(
                {STATE: obs[STATE][i], IMAGE_KEY: obs[IMAGE_KEY][i], ACTION: a[i], "task": DESCRIPTION}
            )
        env.step(a + noise * rng.standard_normal(a.shape))
    for ep in frames:
        for f in ep:
            ds.add_frame(f)
        ds.save_episode()
    ds.finalize()
    out = outcome(env)
    return {
        "episodes": episodes,
        "frames": episodes * HORIZON,
        "success": sum(o["success"] for o in out),
        "user_success": sum(o["user"] for o in out),
    }


def rollouts(controller, seeds: list[int], batch_seed: int = 0) -> list[dict]:
    """One episode per seed, all as one batch through ``controller`` (prop's LeRobot Controller or a
    KeyedPolicy): the sampler's noise comes from ``batch_seed`` and the call's number, so every
    condition run on the same seeds draws the same noise (paired)."""
    env = Env(seeds)
    controller.reset(batch_seed)
    for _ in range(HORIZON):
        env.step(controller.select_action(env.observation()))
    return outcome(env)
