"""examples/pointmass_diffusion (issue 43): the task's world, expert, image and criteria, and the
table's statistics (the paired sign test, the pooled ratio and the bar)."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from examples.pointmass_diffusion import pipeline as p  # noqa: E402
from examples.pointmass_diffusion import task as pm  # noqa: E402


def test_expert_reaches_its_goal_and_the_user_expert_the_moved_one():
    env = pm.Env(list(range(40)))
    for _ in range(pm.HORIZON):
        env.step(env.expert())
    out = pm.outcome(env)
    assert all(o["success"] and not o["user"] for o in out) and max(abs(o["lean"]) for o in out) < 0.01
    env = pm.Env(list(range(40)))
    for _ in range(pm.HORIZON):
        env.step(env.expert(pm.USER_OFFSET))
    out = pm.outcome(env)
    assert all(o["user"] and not o["success"] for o in out)
    assert np.allclose([o["lean"] for o in out], 0.3, atol=0.01)


def test_image_shows_the_goal_red_and_the_point_blue_where_they_are():
    img = pm.render(np.array([[-0.5, 0.5]]), np.array([[0.5, -0.5]]))[0]
    assert img.shape == (pm.IMAGE, pm.IMAGE, 3) and img.dtype == np.uint8
    row, col = np.unravel_index(img[..., 0].argmax(), img.shape[:2])
    assert col > pm.IMAGE / 2 > row  # the goal: x right, y up the rows
    row, col = np.unravel_index(img[..., 2].argmax(), img.shape[:2])
    assert row > pm.IMAGE / 2 > col
    assert img[..., 1].max() == 0


def test_episodes_of_one_seed_are_the_same_in_any_batch():
    a, b = pm.Env([5, 6, 7]), pm.Env([7])
    assert np.array_equal(a.goal[2], b.goal[0]) and np.array_equal(a.position[2], b.position[0])


def test_sign_test_and_the_bar(tmp_path):
    offline = os.environ.get("HF_HUB_OFFLINE")  # the table imports nothing that sets it for the process
    assert p.sign_p(0, 0) == 1.0 and abs(p.sign_p(0, 10) - 2 / 1024) < 1e-12 and p.sign_p(5, 5) == 1.0

    def write(folder, name, group, wins):
        (tmp_path / folder).mkdir(exist_ok=True)
        eps = [
            {
                "seed": i,
                "success": w,
                "user": 0,
                "distance": 0.1 - 0.05 * w,
                "user_distance": 1.0,
                "lean": 0.0,
            }
            for i, w in enumerate(wins)
        ]
        (tmp_path / folder / f"{name}.json").write_text(
            json.dumps({"name": name, "group": group, "episodes": eps})
        )

    write("judge", "original", "original", [1] * 8 + [0] * 2)
    write("judge", "random-01", "random", [1] * 8 + [0] * 2)
    write("judge", "random-02", "random", [1] * 7 + [0] * 3)
    s = p.summary(tmp_path)["pooled"]
    assert (s["k"], s["n"], s["lost"], s["gained"], s["below_0.9"]) == (15, 20, 1, 0, 1) and not s["bar"]
    write("judge-fixed", "random-02", "random", [1] * 8 + [0] * 2)
    write("judge-fixed", "random-01", "random", [1] * 8 + [0] * 2)
    assert p.summary(tmp_path, "fixed")["pooled"]["bar"]
    # Success re-read at another threshold from the judged final distances (0.05 or 0.1 here).
    at = p.summary(tmp_path, "fixed", threshold=0.2)["pooled"]
    assert (at["k"], at["n"], at["bar"]) == (20, 20, True)
    assert p.summary(tmp_path, threshold=0.01)["pooled"]["k"] == 0
    assert os.environ.get("HF_HUB_OFFLINE") == offline


def test_shared_lerobot_flags_import_without_touching_the_environment():
    """The Diffusion and Eq. 8 flags both LeRobot examples use live in examples/lerobot_common.py: a fresh
    process importing it and this example's pipeline leaves HF_HUB_OFFLINE as it was (importing
    examples.metaworld sets it), and the example trains and personalizes with them."""
    import subprocess

    code = (
        "import os, examples.lerobot_common as c, examples.pointmass_diffusion.pipeline as p; "
        "assert set(c.DIFFUSION) <= set(p.TRAIN) and p.PERSONALIZE[2:] == c.PERSONALIZE_BATCH; "
        "print(os.environ.get('HF_HUB_OFFLINE'))"
    )
    env = {k: v for k, v in os.environ.items() if k != "HF_HUB_OFFLINE"}
    root = Path(__file__).resolve().parents[2]
    env["PYTHONPATH"] = os.pathsep.join([str(root), env.get("PYTHONPATH", "")])
    out = subprocess.run([sys.executable, "-c", code], env=env, cwd=root, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "None"
    assert "--policy.num_inference_steps=10" in p.TRAIN and p.PERSONALIZE[:2] == ["--steps", "300"]
