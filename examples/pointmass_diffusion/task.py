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

from examples.pointmass_diffusion import world
from examples.pointmass_diffusion.world import IMAGE, IMAGE_KEY, SIGMA, SPEED, STATE, render  # noqa: F401

NAME = "reach"
FPS = 10
GAIN = 4.0
HORIZON = 30
THRESHOLD = 0.05
USER_OFFSET = np.array([0.3, 0.0])
USER_CHANGE = "stop 0.3 to the right of the goal (a goal offset)"
USER_BY_DISTANCE = True
NOISE = world.NOISE
ACTION = world.ACTION
DESCRIPTION = "reach the red goal"


def features() -> dict:
    return world.state_feature() | world.image_feature() | world.action_feature()


class Env(world.Square):
    """Every seed an episode, all stepped together (row i: seed ``seeds[i]``)."""

    def expert(self, offset: np.ndarray | None = None) -> np.ndarray:
        target = self.goal + (0 if offset is None else offset)
        return np.clip(GAIN * (target - self.position), -1, 1).astype(np.float32)


def expert(env: Env, user: bool) -> np.ndarray:
    return env.expert(USER_OFFSET if user else None)


def outcome(env: Env) -> list[dict]:
    """Per episode: success, the user's criterion, final distances, lean toward the user's offset."""
    d = np.linalg.norm(env.position - env.goal, axis=1)
    du = np.linalg.norm(env.position - env.goal - USER_OFFSET, axis=1)
    lean = (env.position - env.goal) @ (USER_OFFSET / np.linalg.norm(USER_OFFSET))
    return world.episodes(env, d < THRESHOLD, du < THRESHOLD, d, du, lean)


def record(
    root: Path, episodes: int, seed0: int, offset: np.ndarray | None = None, noise: float = NOISE
) -> dict:
    """Expert episodes (seeds seed0, seed0 + 1, ...) into a new LeRobotDataset at ``root`` (the user's:
    ``offset`` not None), HORIZON frames each (world.record)."""
    import sys

    return world.record(sys.modules[__name__], root, episodes, seed0, offset is not None, noise)


def rollouts(controller, seeds: list[int], batch_seed: int = 0) -> list[dict]:
    """One episode per seed, all as one batch through ``controller`` (world.rollouts: paired noise)."""
    import sys

    return world.rollouts(sys.modules[__name__], controller, seeds, batch_seed)
