"""A point-mass task whose user changes the path, not the end (issue 43's second Diffusion task): the
same square, image and state as task.py (reach); the user wants the goal approached from above.

- **Expert**: the base demonstrations go straight to the goal, ``clip(GAIN * (goal - position), -1, 1)``.
  The user's aim at a point above the goal as high as ``LIFT`` times the horizontal distance left,
  ``goal + (0, LIFT * |x - goal x|)``: the point climbs while it closes in and comes down onto the goal
  from above; both end at the goal.
- **Success**: the final distance to the goal under ``THRESHOLD`` (0.1) after ``HORIZON`` steps. The
  user's criterion (a path): the point was ``ABOVE`` or more above the goal while within ``NEAR`` of it
  horizontally (``user_distance``: how far it stayed from that window, 0 when visited). ``lean``: the
  highest it was above the goal while within ``NEAR`` horizontally (capped at 0.5): the original's
  straight approach is low unless it started above, the user's high.
"""

from __future__ import annotations

import numpy as np

from examples.pointmass_diffusion import world

NAME = "waypoint"
FPS = 10
GAIN = 4.0
LIFT = 2.5
HORIZON = 40
TRAIN_STEPS = 500  # lerobot-train steps (reach: 300)
THRESHOLD = 0.1
NEAR, ABOVE = 0.1, 0.15
USER_CHANGE = "come down onto the goal from above (a path)"
USER_BY_DISTANCE = False
DESCRIPTION = "reach the red goal"


def features() -> dict:
    return world.state_feature() | world.image_feature() | world.action_feature()


class Env(world.Square):
    image = True


def expert(env: Env, user: bool) -> np.ndarray:
    target = env.goal.copy()
    if user:
        target[:, 1] += LIFT * np.abs(env.position[:, 0] - env.goal[:, 0])
    return np.clip(GAIN * (target - env.position), -1, 1).astype(np.float32)


def outcome(env: Env) -> list[dict]:
    d = np.linalg.norm(env.position - env.goal, axis=1)
    path = np.stack(env.path, 1) - env.goal[:, None]  # (N, T + 1, 2) relative to the goal
    near = np.abs(path[..., 0]) < NEAR
    height = np.where(near, np.minimum(path[..., 1], 0.5), -np.inf).max(1)
    # How far each path stayed from the window {|dx| < NEAR, dy >= ABOVE} (0: it was in it).
    gap = np.hypot(np.maximum(np.abs(path[..., 0]) - NEAR, 0), np.maximum(ABOVE - path[..., 1], 0)).min(1)
    return world.episodes(env, d < THRESHOLD, gap == 0, d, gap, np.maximum(height, 0.0))
