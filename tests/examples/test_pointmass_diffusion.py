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
    assert "--policy.num_inference_steps=10" in p.TRAIN and p.PERSONALIZE[:2] == ["--steps", "900"]


def _expert_episodes(t, user: bool, seeds=range(1_000_000, 1_000_200)) -> list[dict]:
    env = t.Env(list(seeds))
    for _ in range(t.HORIZON):
        env.step(t.expert(env, user))
    return t.outcome(env)


def test_every_task_defines_what_the_shared_steps_use():
    from examples.pointmass_diffusion import world

    for name in world.TASKS:
        t = world.load(name)
        assert t.NAME == name and t.THRESHOLD > 0 and t.HORIZON > 0 and t.USER_CHANGE
        obs = t.Env([3, 4]).observation()
        assert set(obs) == set(t.features()) - {world.ACTION}
        assert all(len(v) == 2 for v in obs.values())
    assert world.IMAGE_KEY not in world.load("slow").features()  # state only
    assert {world.load(n).THRESHOLD for n in world.TASKS} == {0.05, 0.1, 0.15}


def test_waypoint_task_user_comes_down_from_above_and_both_end_at_the_goal():
    from examples.pointmass_diffusion import task_waypoint as w

    base, user = _expert_episodes(w, False), _expert_episodes(w, True)
    # The path differs, not the end.
    assert all(o["success"] for o in base) and all(o["success"] for o in user)
    rate = [np.mean([o["user"] for o in eps]) for eps in (base, user)]
    assert rate[0] < 0.3 and rate[1] > 0.65  # from above: a start straight below the goal cannot
    assert np.mean([o["lean"] for o in user]) > 2 * np.mean([o["lean"] for o in base])
    assert all((o["user_distance"] == 0) == bool(o["user"]) for o in base + user)


def test_slow_task_user_moves_slowly_and_a_full_speed_episode_fails_its_criterion():
    from examples.pointmass_diffusion import task_slow as s

    base, user = _expert_episodes(s, False), _expert_episodes(s, True)
    assert all(o["success"] for o in base) and all(o["user"] for o in user)
    assert np.mean([o["user"] for o in base]) < 0.1
    top = np.array([o["user_distance"] for o in user])  # the episode's top speed: capped (a near start: less)
    assert top.max() <= s.USER_SPEED + 1e-6 and np.median(top) > s.USER_SPEED - 1e-6
    assert np.mean([o["lean"] for o in user]) > 0.55 > 0.1 > np.mean([o["lean"] for o in base])


def test_wrong_keys_are_16_random_and_16_neighbours_the_random_ones_as_before():
    from examples.lerobot_wrong_keys import key_conditions

    key = np.random.default_rng(0).integers(0, 2, 256).astype(np.uint8)
    cs = p.conditions(key)
    rnd = [c for c in cs if c["group"] == "random"]
    nb = [c for c in cs if c["group"] == "neighbour"]
    assert [c["name"] for c in cs[:3]] == ["original", "no_key", "user_key"]
    assert len(rnd) == len(nb) == 16 and nb[0]["name"] == "neighbour-01" and rnd[-1]["name"] == "random-16"
    before = [w for w in key_conditions(key, 16, 0, 1, 0) if w["group"] == "random"]  # round 1's keys
    assert all(np.array_equal(a["bits"], b["bits"]) for a, b in zip(rnd, before))
    assert sorted(int((c["bits"] != key).sum()) for c in nb) == sorted([1 + i % 8 for i in range(16)])


def test_bar_needs_both_groups_and_every_key(tmp_path):
    def write(folder, name, group, wins):
        (tmp_path / folder).mkdir(exist_ok=True)
        eps = [{"seed": i, "success": w, "user": 0, "distance": 0.2 - 0.1 * w, "user_distance": 0.5,
                "lean": 0.0} for i, w in enumerate(wins)]  # fmt: skip
        row = {"name": name, "group": group, "episodes": eps}
        (tmp_path / folder / f"{name}.json").write_text(json.dumps(row))

    write("judge", "original", "original", [1] * 20)
    write("judge-v", "random-01", "random", [1] * 20)
    s = p.summary(tmp_path, "v")
    assert s["pooled"]["bar"] and s["neighbours"] is None and not s["bar"]  # neighbours not judged
    write("judge-v", "neighbour-01", "neighbour", [1] * 19 + [0])
    s = p.summary(tmp_path, "v")
    assert s["bar"] and s["neighbours"]["ratio"] == 0.95 and s["neighbours"]["lost"] == 1
    write("judge-v", "neighbour-02", "neighbour", [1] * 17 + [0] * 3)
    s = p.summary(tmp_path, "v")
    nb = s["neighbours"]
    assert (nb["k"], nb["n"], nb["below_0.9"], nb["worst"]) == (36, 40, 1, 0.85) and not s["bar"]
    assert nb["farther"] == 2 and nb["farther_episodes"] == 4 and nb["extra_distance"] > 0
    # A task whose user's criterion is no distance keeps it as judged at another threshold.
    from examples.pointmass_diffusion import task_slow

    assert p.summary(tmp_path, "v", 0.6)["rows"][0]["user"] == 20  # 0.5 < 0.6: re-read (reach)
    assert p.summary(tmp_path, "v", 0.6, task_slow)["rows"][0]["user"] == 0


def test_an_out_folder_holds_one_task(tmp_path):
    from examples.pointmass_diffusion import task_slow

    p.check_task(tmp_path / "o", task_slow)
    p.check_task(tmp_path / "o", task_slow)
    code = (
        "import sys; from pathlib import Path; from examples.pointmass_diffusion.__main__ import main; "
        f"main(['table', '--task', 'reach', '--out', {str(tmp_path / 'o')!r}])"
    )
    root = Path(__file__).resolve().parents[2]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")]))
    import subprocess

    out = subprocess.run([sys.executable, "-c", code], env=env, cwd=root, capture_output=True, text=True)
    assert out.returncode != 0 and "Traceback" not in out.stderr
    assert out.stderr.strip().splitlines() == [
        f"prop: error: {tmp_path / 'o'} holds task 'slow', not 'reach': pass --task slow or another --out"
    ]
