"""examples/pointmass_diffusion (issue 43): the task's world, expert, image and criteria, and the
table's statistics (the paired sign test, the pooled ratio and the bar)."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest

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


def _write_block(folder: Path, name: str, group: str, wins: list[int], first_seed: int = 0) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    eps = [{"seed": first_seed + i, "success": w, "user": 0, "distance": 0.2 - 0.1 * w, "user_distance": 0.5,
            "lean": 0.0} for i, w in enumerate(wins)]  # fmt: skip
    (folder / f"{name}.json").write_text(json.dumps({"name": name, "group": group, "episodes": eps}))


def test_blocks_of_seeds_read_alone_or_pooled_and_overlapping_blocks_are_refused(tmp_path):
    """judge --seed-offset N writes judge[-v]/offset-N; the table reads the first block by default (the
    100-episode tables as before), another block alone, or several pooled on their seeds."""
    assert p.judge_dir(tmp_path, "v") == tmp_path / "judge-v"
    assert p.judge_dir(tmp_path, "v", 10) == tmp_path / "judge-v" / "offset-10"
    assert p.judge_dir(tmp_path, "", 10) == tmp_path / "judge" / "offset-10"
    _write_block(tmp_path / "judge", "original", "original", [1] * 10)
    _write_block(tmp_path / "judge" / "offset-10", "original", "original", [1] * 10, 10)
    _write_block(tmp_path / "judge-v", "random-01", "random", [1] * 10)
    _write_block(tmp_path / "judge-v" / "offset-10", "random-01", "random", [1] * 5 + [0] * 5, 10)
    _write_block(tmp_path / "judge-v", "neighbour-01", "neighbour", [1] * 10)  # first block only
    first = p.summary(tmp_path, "v")
    assert (first["pooled"]["k"], first["pooled"]["n"], first["left_out"]) == (10, 10, [])
    assert first["pooled"]["bar"] and first["bar"]
    fresh = p.summary(tmp_path, "v", offsets=[10])
    assert (fresh["pooled"]["k"], fresh["pooled"]["lost"], fresh["neighbours"]) == (5, 5, None)
    both = p.summary(tmp_path, "v", offsets=[0, 10])
    r = both["pooled"]
    assert (r["k"], r["n"], r["lost"], r["gained"], r["below_0.9"]) == (15, 20, 5, 0, 1) and not both["bar"]
    assert both["left_out"] == ["neighbour-01"] and both["neighbours"] is None
    assert abs(r["ratio"] - 0.75) < 1e-12 and abs(r["p"] - p.sign_p(5, 0)) < 1e-12
    _write_block(tmp_path / "judge" / "offset-5", "original", "original", [1] * 10, 5)
    _write_block(tmp_path / "judge-v" / "offset-5", "random-01", "random", [1] * 10, 5)
    with pytest.raises(SystemExit) as e:
        p.summary(tmp_path, "v", offsets=[0, 5])
    assert str(e.value).startswith("prop: error: --seed-offset 0 --seed-offset 5: original's blocks share")


def test_keys_the_paired_test_separates_after_bonferroni(tmp_path):
    """A key that loses 10 of 10 episodes (two-sided sign p = 2/1024) is separated from the original over
    2 keys (p < 0.025) and not over 32 (p < 0.0016)."""
    _write_block(tmp_path / "judge", "original", "original", [1] * 10 + [0] * 10)
    _write_block(tmp_path / "judge-v", "random-01", "random", [0] * 20)
    _write_block(tmp_path / "judge-v", "neighbour-01", "neighbour", [1] * 20)
    s = p.summary(tmp_path, "v")
    assert s["pooled"]["alpha"] == 0.025 and s["pooled"]["worse"] == ["random-01"]
    assert s["neighbours"]["better"] == ["neighbour-01"] and s["neighbours"]["worse"] == []
    for i in range(2, 17):
        _write_block(tmp_path / "judge-v", f"random-{i:02d}", "random", [1] * 10 + [0] * 10)
        _write_block(tmp_path / "judge-v", f"neighbour-{i:02d}", "neighbour", [1] * 10 + [0] * 10)
    s = p.summary(tmp_path, "v")
    assert (
        s["pooled"]["alpha"] == 0.05 / 32 and s["pooled"]["worse"] == [] and s["neighbours"]["better"] == []
    )
    assert s["pooled"]["worst_key"] == "random-01"


class _Still:
    """A controller that never moves the point, remembering the noise seeds it was reset with."""

    def __init__(self, resets: list) -> None:
        self.resets = resets

    def reset(self, seed=None) -> None:
        self.resets.append(seed)

    def select_action(self, obs) -> np.ndarray:
        return np.zeros((len(obs[world_state()]), 2))


def world_state() -> str:
    from examples.pointmass_diffusion import world

    return world.STATE


def test_judge_takes_a_block_of_fresh_seeds_and_keeps_the_first_block_as_it_was(tmp_path, monkeypatch):
    resets: list = []
    names = [("original", "original"), ("no_key", "no_key"), ("random-01", "random")]
    monkeypatch.setattr(p, "conditions", lambda key: [{"name": n, "group": g} for n, g in names])
    monkeypatch.setattr(p, "user_bits", lambda out, variant: np.zeros(8, np.uint8))
    monkeypatch.setattr(p, "controller", lambda out, variant, c: _Still(resets))
    p.step_judge(tmp_path, "v", 3)
    p.step_judge(tmp_path, "v", 4, offset=3)
    first = json.loads((tmp_path / "judge-v" / "random-01.json").read_text())["episodes"]
    fresh = json.loads((tmp_path / "judge-v" / "offset-3" / "random-01.json").read_text())["episodes"]
    assert [e["seed"] for e in first] == [p.JUDGE_SEED + i for i in range(3)]
    assert [e["seed"] for e in fresh] == [p.JUDGE_SEED + 3 + i for i in range(4)]
    assert (tmp_path / "judge" / "offset-3" / "original.json").is_file()
    assert resets == [0, 0, 0, 3, 3, 3]  # the sampler's noise: the first block's as before, then fresh
    # Still where it started: the same seed ends at the same distance in either block's batch.
    assert fresh[0]["distance"] == pm.outcome(pm.Env([p.JUDGE_SEED + 3]))[0]["distance"]
    p.step_judge(tmp_path, "v", 4, offset=3)  # judged: nothing re-run
    assert len(resets) == 6
    with pytest.raises(SystemExit) as e:
        p.step_judge(tmp_path, "v", 5)
    assert str(e.value).startswith(f"prop: error: {tmp_path / 'judge' / 'original.json'} holds seeds ")
    assert str(e.value).endswith("pass --episodes 3 or another --seed-offset")


def test_seed_offset_flag_refuses_bad_blocks_in_one_line(tmp_path, capsys):
    from examples.pointmass_diffusion.__main__ import main

    for argv, why in (
        (["judge", "--seed-offset", "0", "--seed-offset", "100"], "judge takes one block of seeds"),
        (["table", "--seed-offset", "-1"], "--seed-offset -1: an offset is 0 or more"),
        (["table", "--seed-offset", "100", "--seed-offset", "100"], "a block named twice"),
    ):
        with pytest.raises(SystemExit) as e:
            main([*argv, "--out", str(tmp_path / "o")])
        err = capsys.readouterr().err.strip().splitlines()
        assert e.value.code == 2 and len(err) == 1 and err[0].startswith("prop: error: --seed-offset")
        assert why in err[0]
    assert not (tmp_path / "o").exists()


def test_spearman_ranks_ties_and_its_permutation_p():
    rho, pv = p.spearman([1, 1, 2, 3], [1, 2, 3, 4])
    assert abs(rho - 4.5 / np.sqrt(22.5)) < 1e-12  # average ranks of the tie: scipy's value
    rho, pv = p.spearman(range(12), [5 - x for x in range(12)], permutations=2000)
    assert abs(rho + 1) < 1e-12 and pv == 1 / 2001
    rho, pv = p.spearman(range(12), [3, 9, 0, 11, 5, 1, 7, 10, 2, 8, 4, 6], permutations=2000)
    assert abs(rho) < 0.3 and pv > 0.3


def test_code_distances_follow_the_bundles_key_encoding(cli, workdir, capsys):
    """A raw-encoded bundle's neighbour keys are as many code bits from the user's as key bits; hashed,
    as far as random keys. The table relates the wrong keys' final distances to them."""
    import shutil

    from tests.cli.shares import personalize

    (workdir / "user.key").write_bytes((workdir / "k.bin").read_bytes())
    (workdir / "user.key").chmod(0o600)
    assert personalize(cli, workdir, "--key-encoding", "raw", out="bundle-raw").code == 0
    assert personalize(cli, workdir, out="bundle-hashed").code == 0
    raw, hashed = p.code_distances(workdir, "raw"), p.code_distances(workdir, "hashed")
    assert len(raw) == len(hashed) == 32
    user = p.user_bits(workdir, "raw")
    nb = {c["name"]: int((c["bits"] != user).sum()) for c in p.conditions(user) if c["group"] == "neighbour"}
    assert len(nb) == 16 and all(raw[n] == d for n, d in nb.items())
    assert min(hashed[n] for n in nb) > 20 and 50 < np.mean(list(hashed.values())) < 78
    # The table: wrong keys ending farther the farther their code (Spearman +1).
    capsys.readouterr()
    _write_block(workdir / "judge", "original", "original", [1] * 4)
    for n, d in raw.items():
        _write_block(workdir / "judge-raw", n, n.split("-")[0], [1] * 4)
        row = json.loads((workdir / "judge-raw" / f"{n}.json").read_text())
        row["episodes"] = [e | {"distance": d / 1000} for e in row["episodes"]]
        (workdir / "judge-raw" / f"{n}.json").write_text(json.dumps(row))
    p.code_table(workdir, "raw")
    out = capsys.readouterr().out
    assert "32 wrong keys (seed offset 0: 4 episodes)" in out and "mean final distance, Spearman +1.00" in out
    shutil.rmtree(workdir / "bundle-hashed")
    p.code_table(workdir, "hashed")  # no bundle, nothing judged: nothing printed
    assert capsys.readouterr().out == ""
