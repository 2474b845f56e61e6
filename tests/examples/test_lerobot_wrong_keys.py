"""examples/lerobot_wrong_keys.py (issue 32's closed-loop wrong-key harness) on a tiny ACT run."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("lerobot")
pytestmark = pytest.mark.lerobot
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from examples import lerobot_reach_task as task  # noqa: E402
from examples import lerobot_wrong_keys as wk  # noqa: E402
from prop_cli import api  # noqa: E402
from prop_cli.config import PersonalizeConfig  # noqa: E402
from prop_cli.core.key_files import KeySource, generate_key_file, read_key_file  # noqa: E402

TINY = dict(steps=5, user_rows=8, null_rows=4, neighbour_keys=2, random_keys=2, samples_per_key=1,
            eval_random_keys=4, null_weight=2.0, base_lr_scale=0.1)  # fmt: skip


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A tiny examples.lerobot_reach run folder: datasets, the original ACT, user.key, the bundle."""
    d = tmp_path_factory.mktemp("wrong-keys")
    task.record(d / "reach-general", 3, 0, np.zeros(3, np.float32))
    task.record(d / "reach-user", 2, 50_000, task.USER_OFFSET)
    task.train_base(d / "reach-general", d / "act", steps=5)
    generate_key_file(d / "user.key")
    key = read_key_file(d / "user.key", 128)
    api.personalize_checkpoint(str(d / "act"), [(d / "reach-user", KeySource(key, "file"))], d / "bundle",
                               PersonalizeConfig.of(**TINY), general=d / "reach-general")  # fmt: skip
    return d, key


def test_wrong_keys_are_drawn_at_the_distances_asked_and_never_the_users_key():
    key = np.random.default_rng(0).integers(0, 2, 128).astype(np.uint8)
    conds = wk.key_conditions(key, 3, 5, 2, seed=0)
    assert [c["group"] for c in conds] == ["random"] * 3 + ["neighbour"] * 5
    assert [int((c["bits"] != key).sum()) for c in conds[3:]] == [1, 2, 1, 2, 1]
    assert [c["id"]["distance"] for c in conds[3:]] == [1, 2, 1, 2, 1]
    assert all((c["bits"] != key).any() for c in conds)
    assert all(c["id"]["flipped"] == np.flatnonzero(c["bits"] != key).tolist() for c in conds[3:])
    assert "bits" not in conds[3]["id"]  # a neighbour's bits with its flips would give the key away
    fewer = wk.key_conditions(key, 2, 3, 2, seed=0)  # a smaller run measures the first keys of a larger one
    assert all((a["bits"] == b["bits"]).all() for a, b in zip(fewer, conds[:2] + conds[3:6]))


def _row(name: str, group: str, success: float, episodes: list[int] | None = None, **figures) -> dict:
    return {"name": name, "group": group, "success": {"mean": success},
            "per_episode_success": episodes or [round(success)]} | figures  # fmt: skip


def test_gate_counts_paired_losses_and_ranks_offline_figures_against_them():
    rows = [_row("original", "original", 1.0, [1, 1, 1, 1])]
    rows += [_row(f"r{i}", "random", 1 - i / 4, [1] * (4 - i) + [0] * i, fidelity_user=0.01 * i)
             for i in range(3)]  # fmt: skip
    g = wk.gate(rows)
    assert [r["lost"] for r in rows] == [0, 0, 1, 2] and g["failing"] == ["r1", "r2"]
    assert g["predicts"]["fidelity_user"] == pytest.approx(1.0) and g["predicts"]["delta_rms"] is None
    # pooled over the keys: 3 lost, none gained; the exact sign test: 2 x 0.5^3
    assert g["paired"]["random"] == g["paired"]["all"] == {"lost": 3, "gained": 0, "p": pytest.approx(0.25)}
    assert g["paired"]["neighbour"] == {"lost": 0, "gained": 0, "p": 1.0}
    # the user's key and the original only (a bundle's personalization re-measured): no gate to read
    figures = {"preference": {"mean": 0.0}, "return": {"mean": -2.0}}
    alone = [_row("original", "original", 1.0, [1, 1, 1, 1], **figures),
             _row("user key", "user_key", 0.0, [0, 0, 0, 0], **figures)]  # fmt: skip
    report = {"rows": alone} | wk.gate(alone)
    assert not report["passes"] and report["worst"] is None
    assert wk.table(report).endswith("original 1.00; no wrong keys measured: no gate")


def test_sign_test_pools_losses_and_gains_and_ties_do_not_count():
    rows = [{"lost": 9, "gained": 1}, {"lost": 1, "gained": 0}]
    s = wk.sign_test(rows)
    # 10 lost / 1 gained of 11 untied pairs: 2 * (1 + 11) / 2^11
    assert (s["lost"], s["gained"]) == (10, 1) and s["p"] == pytest.approx(24 / 2048)
    assert wk.sign_test([{"lost": 4, "gained": 4}])["p"] == pytest.approx(1.0)


def test_gate_fails_on_one_bad_key_and_on_the_pooled_mean():
    ok = [_row("original", "original", 1.0), _row("r1", "random", 0.9), _row("n1", "neighbour", 1.0)]
    assert wk.gate(ok)["passes"] and wk.gate(ok)["failing"] == []
    one_bad = [*ok, _row("r2", "random", 0.85)]
    g = wk.gate(one_bad)
    assert not g["passes"] and g["failing"] == ["r2"] and g["worst"]["name"] == "r2"
    assert g["worst"]["ratio"] == pytest.approx(0.85)
    # every key >= 0.9x but the pooled mean 0.9 < 0.95x
    pooled = [_row("original", "original", 1.0), _row("r1", "random", 0.9), _row("n1", "neighbour", 0.9)]
    assert not wk.gate(pooled)["passes"] and wk.gate(pooled)["failing"] == []


def test_harness_rolls_out_every_key_on_the_same_seeds_and_writes_json(run, capsys):
    d, _ = run
    report = wk.main(["--out", str(d), "--episodes", "2", "--random-keys", "2", "--neighbours", "2",
                      "--max-flip", "8", "--offline-frames", "8"])  # fmt: skip
    rows = report["rows"]
    assert [r["group"] for r in rows] == ["original", "no_key", "user_key", "random", "neighbour",
                                          "random", "neighbour"]  # fmt: skip  # interleaved
    assert [r["name"] for r in rows[3:]] == ["random 1", "neighbour d=1", "random 2", "neighbour d=2"]
    assert all(r["episodes"] == 2 for r in rows)
    assert report["env"] == task.ENV_ID  # the run's datasets name their simulator (MuJoCo's reach)
    # the offline figures are taken against the original itself
    assert rows[0]["fidelity_user"] == rows[0]["fidelity_general"] == rows[0]["leakage_user"] == 0.0
    assert rows[0]["personalization_user"] == pytest.approx(0.0, abs=1e-6)  # 1 - mse(b, p) / mse(b, p)
    assert all(r["personalization_user"] <= 1.0 for r in rows)
    assert rows[2]["code_distance"] == 0.0 and rows[2]["delta_cos_user"] == pytest.approx(1.0, abs=1e-5)
    assert all(0.0 < r["code_distance"] < 1.0 for r in rows[3:])
    assert all(r["fidelity_general"] >= 0 and "leakage_user" in r for r in rows[2:])
    saved = json.loads((d / "wrong-keys-bundle.json").read_text())
    assert saved["passes"] == report["passes"] and len(saved["rows"]) == 7 and saved["partial"] is False
    assert not (d / "wrong-keys-bundle.json.part").exists()
    assert "gate (each >= 0.9x, pooled >= 0.95x)" in capsys.readouterr().out
    # paired on the seeds: a row's episodes lost and gained against the original add up to its difference
    for r in rows:
        assert r["gained"] - r["lost"] == round(2 * (r["success"]["mean"] - rows[0]["success"]["mean"]))
    again = wk.main(["--out", str(d), "--from-json", str(d / "wrong-keys-bundle.json")])
    assert again["failing"] == report["failing"] and again["pooled"] == report["pooled"]


def test_a_stopped_run_keeps_every_key_measured_so_far(run, tmp_path, monkeypatch):
    """The report is rewritten whole after each condition: stopped after the first wrong key, the JSON holds
    the four conditions measured, marked partial, and no half-written file."""
    d, _ = run
    measure = wk.measure

    def stopped(args, save):
        def save_then_stop(report):
            save(report)
            if len(report["rows"]) == 4:
                raise KeyboardInterrupt

        return measure(args, save_then_stop)

    monkeypatch.setattr(wk, "measure", stopped)
    path = tmp_path / "report.json"
    with pytest.raises(KeyboardInterrupt):
        wk.main(["--out", str(d), "--episodes", "1", "--random-keys", "2", "--neighbours", "2",
                 "--offline-frames", "0", "--json", str(path)])  # fmt: skip
    saved = json.loads(path.read_text())
    assert saved["partial"] is True and not path.with_name("report.json.part").exists()
    assert [r["group"] for r in saved["rows"]] == ["original", "no_key", "user_key", "random"]
    assert wk.main(["--out", str(d), "--from-json", str(path)])["failing"] == saved["failing"]


def test_wrong_keys_run_interleaved_each_group_in_its_own_order():
    wrong = [{"group": "random", "i": i} for i in range(3)] + [{"group": "neighbour", "i": 0}]
    order = [(w["group"][0], w["i"]) for w in wk.interleaved(wrong)]
    assert order == [("r", 0), ("n", 0), ("r", 1), ("r", 2)]
    assert wk.interleaved([]) == []


def test_the_examples_no_eval_trains_the_bundle_and_rolls_out_nothing(run):
    """lerobot_reach's --no-eval (the harness measures the keys instead): run_bundle with 0 episodes trains
    the bundle, keeps personalize's offline report and runs no `prop eval`."""
    from examples import lerobot_reach as reach

    d, _ = run
    flags = "--steps 3 --user-rows 8 --null-rows 4 --neighbour-keys 2 --random-keys 2 --samples-per-key 1"
    figures = reach.run_bundle(d, "no-eval", flags.split(), 0, "act")
    assert "eval_s" not in figures and "closed_loop" not in figures
    assert 0 < figures["personalize_s"] and isinstance(figures["offline"]["personalization"], float)
    assert (d / "no-eval" / "manifest.json").is_file()


def test_a_sealed_bundle_is_refused_in_one_line(run, tmp_path):
    d, key = run
    api.personalize_checkpoint(str(d / "act"), [(d / "reach-user", KeySource(key, "file"))], d / "sealed",
                               PersonalizeConfig.of(**TINY, seal=True))  # fmt: skip
    with pytest.raises(SystemExit, match="is sealed"):
        wk.main(["--out", str(d), "--bundle", "sealed", "--episodes", "1", "--offline-frames", "0"])


def test_paper_reach_without_panda_gym_is_refused_in_one_line_before_deleting(tmp_path, monkeypatch):
    from examples import lerobot_reach

    monkeypatch.setitem(sys.modules, "panda_gym", None)  # import fails as if not installed
    (tmp_path / "figures.json").write_text("{}")  # an earlier run, kept
    with pytest.raises(SystemExit) as e:
        lerobot_reach.main(["--sim", "panda", "--out", str(tmp_path)])
    line = str(e.value.code)
    assert "\n" not in line and "panda-gym" in line and "'.[rl]'" in line and "--sim mujoco" in line
    assert (tmp_path / "figures.json").is_file()


def test_a_run_recorded_on_panda_gym_asks_for_it(run, tmp_path, monkeypatch):
    d, _ = run
    assert task.sim_of(d / "reach-general") == "mujoco"
    old = tmp_path / "old"
    (old / "reach-general" / "meta").mkdir(parents=True)
    for name in ("act", "bundle", "user.key"):
        (old / name).symlink_to(d / name)
    info = json.loads((d / "reach-general" / "meta" / "info.json").read_text()) | {"robot_type": "panda"}
    (old / "reach-general" / "meta" / "info.json").write_text(json.dumps(info))
    assert task.sim_of(old / "reach-general") == "panda"  # runs recorded before issue 38 say "panda"
    monkeypatch.setitem(sys.modules, "panda_gym", None)
    with pytest.raises(SystemExit, match=r"needs panda-gym.*\[rl\]"):
        wk.main(["--out", str(old), "--episodes", "1", "--offline-frames", "0"])


def test_a_tiny_pi0_run_is_measured_under_pi_tinys_patch(tmp_path):
    """--policy pi0: the original and the bundle load only under examples.pi_tiny's size patch, which the
    harness applies itself (the caller holds none), with the run's instruction and camera."""
    from examples import lerobot_reach as reach
    from examples import pi_tiny

    d = tmp_path
    task.record(d / "reach-general", 2, 0, np.zeros(3, np.float32), camera=True, goal_in_state=True)
    task.record(d / "reach-user", 2, 50_000, task.USER_OFFSET, camera=True, goal_in_state=True)
    task.train_base(d / "reach-general", d / "pi0", steps=2, lr=1e-3, kind="pi0", built=reach.pi(d, "pi0"))
    key = np.random.default_rng(1).integers(0, 2, 32).astype(np.uint8)  # 32 bits: fewer 1-bit neighbours
    (d / "user.key").write_bytes(np.packbits(key).tobytes())
    (d / "user.key").chmod(0o600)
    with pi_tiny.tiny():
        api.personalize_checkpoint(str(d / "pi0"), [(d / "reach-user", KeySource(key, "file"))], d / "bundle",
                                   PersonalizeConfig.of(**TINY), general=d / "reach-general")  # fmt: skip
    report = wk.main(["--out", str(d), "--policy", "pi0", "--episodes", "1", "--random-keys", "1",
                      "--neighbours", "1", "--offline-frames", "4"])  # fmt: skip
    assert report["policy"] == "pi0" and report["env"] == task.env_id("mujoco", True)
    assert [r["group"] for r in report["rows"]] == ["original", "no_key", "user_key", "random", "neighbour"]
    assert json.loads((d / "wrong-keys-bundle.json").read_text())["partial"] is False
    assert report["rows"][0]["fidelity_user"] == 0.0  # the original, rebuilt under the patch, against itself
    assert report["rows"][2]["code_distance"] == 0.0 and report["rows"][4]["key"]["distance"] == 1
