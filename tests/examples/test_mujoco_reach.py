"""examples/mujoco_reach.py, the LeRobot tests' closed-loop task (issue 38): PandaReach's interface on
MuJoCo, its camera, and the set-up's rendering check. Runs where mujoco is installed (.venv-lerobot)."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

# mujoco is not imported here: examples.mujoco_reach sets MUJOCO_GL before it does.
if importlib.util.find_spec("mujoco") is None:
    pytest.skip("needs mujoco (the lerobot-test extra: scripts/setup-lerobot.sh)", allow_module_level=True)
pytestmark = pytest.mark.lerobot
ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from examples import lerobot_reach_task as task  # noqa: E402
from examples import mujoco_reach as reach  # noqa: E402
from prop_cli.run.envs import make_env  # noqa: E402


def expert_episode(env, seed: int, offset=task.USER_OFFSET * 0, steps: int = 30):
    obs, _ = env.reset(seed=seed)
    trace = [obs]
    for _ in range(steps):
        obs, reward, terminated, truncated, info = env.step(task.expert(obs, offset))
        trace.append(obs)
        if terminated:
            break
    return trace, reward, terminated, info


def test_the_expert_reaches_every_goal_and_success_ends_the_episode():
    env = make_env(task.ENV_ID)
    for seed in range(10):
        trace, reward, terminated, info = expert_episode(env, seed)
        last = trace[-1]
        d = np.linalg.norm(last["achieved_goal"] - last["desired_goal"])
        assert terminated and info["is_success"] and reward == 0.0 and d < task.SUCCESS
        assert len(trace) - 1 <= 6  # a few 5 cm steps from the start to any goal in the box
        assert np.allclose(last["observation"][:3], last["achieved_goal"])
    env.close()


def test_the_user_offset_is_reachable_and_judged_by_the_metric():
    env = make_env(task.ENV_ID)
    trace, *_ = expert_episode(reach.MujocoReach(), 7, task.USER_OFFSET)  # no stop on success: 30 steps
    assert len(trace) == 31 and task.user_preference({"observations": trace}) == 1.0
    trace, *_ = expert_episode(env, 7)
    assert task.user_preference({"observations": trace}) == 0.0  # the goal itself is 10 cm off it
    env.close()


def test_actions_move_at_most_five_centimetres_and_are_clipped():
    env = reach.MujocoReach()
    obs, _ = env.reset(seed=0)
    for a in ([1, 0, 0], [0, -1, 0], [0, 0, 1], [5, 5, 5]):
        before = obs["achieved_goal"].copy()
        obs, *_ = env.step(np.array(a, np.float32))
        moved = obs["achieved_goal"] - before
        assert np.linalg.norm(moved) <= reach.STEP * np.sqrt(3) + 1e-3
        assert np.sign(moved[np.nonzero(a)[0]]).tolist() == np.sign(np.array(a)[np.nonzero(a)[0]]).tolist()
    assert np.linalg.norm(obs["observation"][3:]) > 0  # the velocity is in the state
    for _ in range(40):
        obs, *_ = env.step(np.ones(3, np.float32))
    assert np.allclose(obs["achieved_goal"], reach.HIGH, atol=0.01)  # held at the workspace's edge


def test_the_same_seed_gives_the_same_episode_and_goals_stay_in_the_box():
    env = reach.MujocoReach()
    goals = np.stack([env.reset(seed=s)[0]["desired_goal"] for s in range(50)])
    assert (goals >= reach.GOAL_LOW - 1e-6).all() and (goals <= reach.GOAL_HIGH + 1e-6).all()
    assert len(np.unique(goals.round(4), axis=0)) == 50
    a, *_ = expert_episode(env, 3, steps=5)
    b, *_ = expert_episode(env, 3, steps=5)
    assert all(np.array_equal(x["observation"], y["observation"]) for x, y in zip(a, b))


def test_the_camera_task_shows_the_goal_where_it_is():
    env = make_env(task.CAMERA_ENV_ID)
    frames = []
    for seed in (0, 1):
        obs, _ = env.reset(seed=seed)
        assert obs["pixels"].shape == (task.IMAGE, task.IMAGE, 3) and obs["pixels"].dtype == np.uint8
        assert np.array_equal(obs[task.STATE_GOAL], task.state_goal(obs))
        frames.append(obs["pixels"])
    green = [np.argwhere(f[..., 1].astype(int) - f[..., [0, 2]].max(-1) > 60).mean(0) for f in frames]
    assert not np.isnan(green).any() and np.abs(green[0] - green[1]).max() >= 1  # the goal moved in view
    obs, *_ = env.step(np.array([0, 0, 1], np.float32))
    assert not np.array_equal(obs["pixels"], frames[-1])  # the end effector moved in view
    env.close()


def test_the_rendering_check_passes_here_and_fails_in_one_line_naming_the_packages():
    run = [sys.executable, "-m", "examples.mujoco_reach", "--check-rendering"]
    ok = subprocess.run(run, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0 and ok.stdout.startswith("ok: MuJoCo"), ok.stderr
    env = {**os.environ, "MUJOCO_GL": "no-such-backend"}
    bad = subprocess.run(run, cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert bad.returncode == 1 and bad.stdout == ""
    line = bad.stderr.strip()
    assert "\n" not in line and "Traceback" not in line and "MUJOCO_GL=no-such-backend" in line
    assert "apt-get install libegl1" in line and "libosmesa6" in line
