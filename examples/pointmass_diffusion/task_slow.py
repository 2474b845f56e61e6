"""A point-mass task seen through its state only, whose user changes the speed (issue 43's third Diffusion
task): the same square as task.py (reach), no camera.

- **Observation**: ``observation.state`` = (x, y) and ``observation.environment_state`` = (goal x,
  goal y), no image (LeRobot's Diffusion needs an image or an environment state).
- **Expert**: the base demonstrations go to the goal at full speed, ``clip(GAIN * (goal - position), -1,
  1)``; the user's at most ``USER_SPEED`` of it (each component clipped to +-``USER_SPEED``).
- **Success**: the final distance to the goal under ``THRESHOLD`` (0.15) after ``HORIZON`` steps. The
  user's criterion (a speed): the episode's top commanded speed (the larger component of the clipped
  action, over all steps) under ``SLOW`` (``user_distance``: that speed). ``lean``: one minus it (the
  original near 0 unless it started next to the goal, the user's key near 1 - USER_SPEED).
"""

from __future__ import annotations

import numpy as np

from examples.pointmass_diffusion import world

NAME = "slow"
FPS = 10
GAIN = 4.0
HORIZON = 30
TRAIN_STEPS = 1000  # lerobot-train steps (reach: 300): no image encoder, cheap
THRESHOLD = 0.15
USER_SPEED = 0.4
SLOW = 0.6
USER_CHANGE = f"move at most {USER_SPEED} of full speed (a speed)"
USER_BY_DISTANCE = False
DESCRIPTION = "reach the goal"


ENV_STATE = "observation.environment_state"


def features() -> dict:
    return {
        world.STATE: {"dtype": "float32", "shape": (2,), "names": ["x", "y"]},
        ENV_STATE: {"dtype": "float32", "shape": (2,), "names": ["goal_x", "goal_y"]},
    } | world.action_feature()


class Env(world.Square):
    image = False

    def observation(self) -> dict[str, np.ndarray]:
        return {world.STATE: self.position.astype(np.float32), ENV_STATE: self.goal.astype(np.float32)}


def expert(env: Env, user: bool) -> np.ndarray:
    cap = USER_SPEED if user else 1.0
    return np.clip(GAIN * (env.goal - env.position), -cap, cap).astype(np.float32)


def outcome(env: Env) -> list[dict]:
    d = np.linalg.norm(env.position - env.goal, axis=1)
    speed = np.abs(np.stack(env.actions, 1)).max((1, 2))  # (N,)
    return world.episodes(env, d < THRESHOLD, speed < SLOW, d, speed, 1 - speed)
