"""Steps 2-5 of examples/metaworld: train (lerobot-train), personalize (prop personalize, unsealed and
--seal), judge (closed loop in LeRobot's MetaworldEnv, every key condition on the same seeds), table."""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from examples.lerobot_common import DIFFUSION, PERSONALIZE_BATCH, lerobot_train_args, original_controller
from examples.metaworld import task as mw

BIN = Path(sys.executable).parent
# Small policies that train in minutes on 2 CPU cores (ResNet-18 from scratch: no download).
TRAIN = {
    "act": [
        "--policy.type=act",
        "--policy.dim_model=128",
        "--policy.n_heads=4",
        "--policy.dim_feedforward=512",
        "--policy.n_encoder_layers=2",
        "--policy.n_decoder_layers=1",
        "--policy.chunk_size=20",
        "--policy.n_action_steps=10",
        "--policy.optimizer_lr=3e-4",
        "--policy.optimizer_lr_backbone=3e-4",
        "--steps=1500",
        "--batch_size=16",
    ],
    "diffusion": [
        "--policy.type=diffusion",
        "--policy.down_dims=[64,128,256]",
        *DIFFUSION,
        "--steps=3000",
        "--batch_size=16",
    ],
}
BACKBONE = {p: ["--policy.pretrained_backbone_weights=null"] for p in ("act", "diffusion")}
# prop personalize (the PandaReach example's Eq. 8 batch, fewer steps: every row runs the ResNet).
PERSONALIZE = ["--steps", "500", *PERSONALIZE_BATCH]
SEALED = ["--seal", "--steps", "500", "--user-rows", "32", "--payload-lr", "1e-3"]
JUDGE_SEED = 1_000_000  # recording used 0-39 and 50,000-50,014
EPISODES = {"original": 8, "no_key": 8, "user_key": 8, "wrong": 4}  # per condition; wrong: per key
N_RANDOM, N_NEIGHBOURS, MAX_FLIP = 16, 16, 8


def policy_dir(out: Path, t: str, p: str) -> Path:
    return out / t / p / "train" / "checkpoints" / "last" / "pretrained_model"


def run(cmd: list, log: Path | None = None) -> None:
    print("$ " + " ".join(map(str, cmd)), flush=True)
    if log:
        log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "w") if log else open("/dev/null", "w") as f:
        subprocess.run(list(map(str, cmd)), check=True, stdout=f if log else None, stderr=subprocess.STDOUT)


def step_train(out: Path, tasks: list[str], policies: list[str]) -> None:
    for t in tasks:
        for p in policies:
            if (policy_dir(out, t, p) / "model.safetensors").is_file():
                print(f"train: {policy_dir(out, t, p)} done")
                continue
            train = out / t / p / "train"
            shutil.rmtree(train, ignore_errors=True)
            t0 = time.perf_counter()
            policy = ["--dataset.video_backend=pyav", *TRAIN[p], *BACKBONE[p]]
            job = f"metaworld-{t}-{p}"
            args = lerobot_train_args(f"local/{t}-base", out / t / "base", policy, train, job)
            run([BIN / "lerobot-train", *args], log=out / t / p / "train.log")
            (out / t / p / "train.json").write_text(
                json.dumps({"seconds": round(time.perf_counter() - t0, 1)})
            )
            print(f"train: {t} {p} {time.perf_counter() - t0:.0f} s", flush=True)


def prop(*args) -> str:
    cmd = [sys.executable, "-m", "prop_cli.cli.main", *map(str, args)]
    print("$ prop " + " ".join(map(str, args)), flush=True)
    return subprocess.run(cmd, check=True, stdout=subprocess.PIPE, text=True).stdout


def step_personalize(out: Path, tasks: list[str], policies: list[str]) -> None:
    key = out / "user.key"
    if not key.is_file():
        prop("keygen", key)
    for t in tasks:
        for p in policies:
            for name, flags in (("bundle", PERSONALIZE), ("bundle-sealed", SEALED)):
                dest = out / t / p / name
                if (dest / "manifest.json").is_file():
                    print(f"personalize: {dest} done")
                    continue
                shutil.rmtree(dest, ignore_errors=True)
                t0 = time.perf_counter()
                general = ["--general-data", out / t / "base"] if name == "bundle" else []
                report = json.loads(
                    prop(
                        "personalize",
                        policy_dir(out, t, p),
                        "--data",
                        out / t / "user",
                        "--key-file",
                        key,
                        "--out",
                        dest,
                        *flags,
                        *general,
                        "--json",
                    )
                )
                report["seconds"] = round(time.perf_counter() - t0, 1)
                (out / t / p / f"{name}.json").write_text(json.dumps(report, indent=1, default=str))
                print(
                    f"personalize: {dest} {report['seconds']} s, personalization "
                    f"{report['metrics'][0]['personalization']:.3f}",
                    flush=True,
                )


def rollouts(task: str, controller, seeds: list[int], horizon: int = mw.HORIZON) -> list[dict]:
    """One episode per seed in LeRobot's MetaworldEnv: MetaWorld's success (the episode ends on it, as in
    LeRobot's env) within ``horizon`` steps, and the user's criterion on the hand where it ends."""
    import torch

    env = mw.Env(task)
    out = []
    for seed in seeds:
        obs = env.reset(seed)
        object0 = env.object0.copy()
        controller.reset(seed)
        success, steps = False, 0
        while steps < horizon:
            steps += 1
            x = {
                mw.STATE: torch.as_tensor(np.asarray(obs["agent_pos"], np.float32)),
                mw.IMAGE_KEY: mw.frame(obs["pixels"]),
            }
            obs, _, terminated, _, info = env.step(np.asarray(controller.select_action(x), np.float32))
            success = success or bool(info.get("is_success"))
            if terminated:
                break
        final = mw.hand(obs)
        out.append(
            {
                "seed": seed,
                "success": int(success),
                "steps": steps,
                "user": int(mw.user_success(final, object0, task)),
                "user_distance": mw.user_distance(final, object0, task),
            }
        )
    env.close()
    return out


def conditions(key: np.ndarray) -> list[dict]:
    from examples.lerobot_wrong_keys import key_conditions

    wrong = key_conditions(key, N_RANDOM, N_NEIGHBOURS, MAX_FLIP, 0)
    rnd = [w for w in wrong if w["group"] == "random"]
    nb = [w for w in wrong if w["group"] == "neighbour"]
    out = [
        {"name": "original", "group": "original"},
        {"name": "no_key", "group": "no_key"},
        {"name": "user_key", "group": "user_key"},
    ]
    for i in range(max(len(rnd), len(nb))):  # interleaved: a stopped run has both kinds
        for j, w in ((i, rnd[i] if i < len(rnd) else None), (i, nb[i] if i < len(nb) else None)):
            if w is not None:
                name = f"random-{j + 1:02d}" if w["group"] == "random" else f"neighbour-{j + 1:02d}"
                out.append({"name": name, **w})
    return out


def judge_original(out: Path, t: str, p: str) -> None:
    """The original alone (it needs no bundle): judge/original.json."""
    path = out / t / p / "judge" / "original.json"
    if path.is_file():
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    seeds = [JUDGE_SEED + i for i in range(EPISODES["original"])]
    t0 = time.perf_counter()
    eps = rollouts(t, original_controller(policy_dir(out, t, p)), seeds)
    row = {"name": "original", "group": "original", "id": None, "episodes": eps,
           "seconds": round(time.perf_counter() - t0, 1)}  # fmt: skip
    path.write_text(json.dumps(row, indent=1))
    k, u, n = sum(e["success"] for e in eps), sum(e["user"] for e in eps), len(eps)
    print(f"judge {t} {p} original       success {k}/{n}  user's criterion {u}/{n}  ({row['seconds']} s)")


def step_judge(out: Path, tasks: list[str], policies: list[str]) -> None:
    from prop_cli.bundle import load_bundle
    from prop_cli.core.key_files import key_for_bundle
    from prop_cli.run import KeyedPolicy

    for t in tasks:
        for p in policies:
            judged = out / t / p / "judge"
            judged.mkdir(parents=True, exist_ok=True)
            bundle = load_bundle(out / t / p / "bundle")
            key = key_for_bundle(bundle.manifest, out / "user.key")
            for c in conditions(key):
                path = judged / f"{c['name']}.json"
                claim = path.with_suffix(".running")  # a second judge process takes the next condition
                if path.is_file() or claim.is_file():
                    continue
                claim.write_text(str(os.getpid()))
                n = EPISODES.get(c["group"], EPISODES["wrong"])
                seeds = [JUDGE_SEED + i for i in range(n)]
                if c["group"] == "original":
                    judge_original(out, t, p)
                    claim.unlink()
                    continue
                if c["group"] == "no_key":
                    ctl = KeyedPolicy(bundle, None)
                elif c["group"] == "user_key":
                    ctl = KeyedPolicy(bundle, key)
                else:  # through the encoder, unchecked: what someone holding the files runs
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        ctl = KeyedPolicy(bundle, c["bits"], method=True)
                t0 = time.perf_counter()
                eps = rollouts(t, ctl, seeds)
                row = {
                    "name": c["name"],
                    "group": c["group"],
                    "id": c.get("id"),
                    "episodes": eps,
                    "seconds": round(time.perf_counter() - t0, 1),
                }
                path.write_text(json.dumps(row, indent=1))
                claim.unlink()
                print(
                    f"judge {t} {p} {c['name']:14s} success {sum(e['success'] for e in eps)}/{n}  user's "
                    f"criterion {sum(e['user'] for e in eps)}/{n}  ({row['seconds']} s)",
                    flush=True,
                )


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    if n == 0:
        return (float("nan"), float("nan"))
    p = k / n
    d = 1 + z * z / n
    c = (p + z * z / (2 * n)) / d
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return (max(0.0, c - h), min(1.0, c + h))


def _cell(k: int, n: int) -> str:
    lo, hi = wilson(k, n)
    return f"{k}/{n} = {k / n:.2f} [{lo:.2f}, {hi:.2f}]" if n else "n/a"


def step_table(out: Path, tasks: list[str], policies: list[str]) -> None:
    """The table of examples/RESULTS.md from the judged conditions (95% Wilson intervals)."""
    head = (
        "| task | policy | original: success | no key: success | wrong keys pooled: success | "
        "worst wrong key | user key: user's criterion | user key: success | original: user's criterion |"
    )
    print(head + "\n|" + " --- |" * 9)
    for t in tasks:
        for p in policies:
            rows = {}
            for f in sorted((out / t / p / "judge").glob("*.json")):
                r = json.loads(f.read_text())
                rows[r["name"]] = r
            if not rows:
                continue

            def k(name, field="success", rows=rows):
                eps = rows[name]["episodes"] if name in rows else []
                return sum(e[field] for e in eps), len(eps)

            wrong = [r for r in rows.values() if r["group"] in ("random", "neighbour")]
            kw = sum(e["success"] for r in wrong for e in r["episodes"])
            nw = sum(len(r["episodes"]) for r in wrong)
            worst = min(wrong, key=lambda r: sum(e["success"] for e in r["episodes"])) if wrong else None
            ws = (
                f"{worst['name']} {sum(e['success'] for e in worst['episodes'])}/{len(worst['episodes'])}"
                if worst
                else "n/a"
            )
            nr = sum(r["group"] == "random" for r in wrong)
            nn = sum(r["group"] == "neighbour" for r in wrong)
            print(
                f"| {t} | {p} | {_cell(*k('original'))} | {_cell(*k('no_key'))} | {_cell(kw, nw)} "
                f"({nr} random, "
                f"{nn} neighbours) | {ws} | {_cell(*k('user_key', 'user'))} | {_cell(*k('user_key'))} | "
                f"{_cell(*k('original', 'user'))} |"
            )
            # paired: per seed, how many wrong-key episodes differ from the original's
            if "original" in rows and wrong:
                ref = {e["seed"]: e["success"] for e in rows["original"]["episodes"]}
                lost = sum(ref[e["seed"]] == 1 and e["success"] == 0 for r in wrong for e in r["episodes"])
                gained = sum(ref[e["seed"]] == 0 and e["success"] == 1 for r in wrong for e in r["episodes"])
                print(
                    f"\n{t} {p}: wrong-key episodes against the original on the same seeds: lost {lost}, "
                    f"gained {gained} of {nw}"
                )
    lerobot_eval_table(out, tasks, policies)


def lerobot_eval_table(out: Path, tasks: list[str], policies: list[str]) -> None:
    """What lerobot-eval itself wrote (eval_info.json): MetaWorld's success per episode, per condition."""
    lines = []
    for t in tasks:
        for p in policies:
            for info in sorted((out / t / p / "lerobot-eval").glob("*/eval_info.json")):
                r = json.loads(info.read_text())
                wins = [bool(w) for task in r["per_task"] for w in task["metrics"]["successes"]]
                eps = ", ".join("pass" if w else "fail" for w in wins)
                lines.append(f"| {t} | {p} | {info.parent.name} | {sum(wins)}/{len(wins)} | {eps} | "
                             f"{r['overall']['eval_s']:.0f} s |")  # fmt: skip
    if lines:
        print("\n| task | policy | lerobot-eval condition | success | episodes | wall |\n|" + " --- |" * 6)
        print("\n".join(lines))


LEROBOT_EVAL_EPISODES = 4


def lerobot_eval_command(
    out: Path, t: str, p: str, name: str, bundle: str, key: Path | None, n: int, encoder: bool = False
) -> list:
    """``lerobot-eval --policy.type=prop`` (the plugin) on LeRobot's MetaWorld env, 480 x 480 frames
    resized to the bundle's by the plugin; LeRobot's own 500-step episodes, ended on MetaWorld's success.
    ``encoder``: the key through the unsealed bundle's encoder (--policy.through_encoder), as anyone
    holding the files can run a wrong key."""
    cmd = [BIN / "lerobot-eval", "--policy.type=prop", f"--policy.bundle={out / t / p / bundle}",
           "--policy.resize_images=true", "--env.type=metaworld", f"--env.task={t}",
           f"--eval.n_episodes={n}", "--eval.batch_size=1",
           f"--output_dir={out / t / p / 'lerobot-eval' / name}"]  # fmt: skip
    if key is not None:
        cmd += [f"--policy.key_file={key}", "--policy.allow_unenrolled_key=true"]
    if encoder:
        cmd += ["--policy.through_encoder=true"]
    return cmd


LEROBOT_EVAL_WRONG_KEYS = 3  # random keys through the unsealed encoder, in lerobot-eval itself


def step_lerobot_eval(out: Path, tasks: list[str], policies: list[str], user_key: bool = True) -> None:
    """MetaWorld's success by LeRobot's own evaluator, through the plugin: the sealed bundle without a key
    (the original, bit for bit), the user's key on both bundles, wrong keys through the unsealed encoder
    (--policy.through_encoder) and a wrong key on the sealed bundle (its base: the original). The
    larger wrong-key sweep is step_judge's (the same policy and resize in Python, shorter episodes)."""
    for t in tasks:
        for p in policies:
            wrong = out / "wrong.key"
            if not wrong.is_file():
                prop("keygen", wrong)
            wrongs = [out / f"wrong-{i}.key" for i in range(LEROBOT_EVAL_WRONG_KEYS)]
            for w in wrongs:
                if not w.is_file():
                    prop("keygen", w)
            # The user's key last: its episodes never meet MetaWorld's success (the hand stays above the
            # button), so each runs LeRobot's whole 500 steps.
            conditions = [("sealed-no-key", "bundle-sealed", None, False),
                          *[(f"encoder-wrong-key-{i}", "bundle", w, True) for i, w in enumerate(wrongs)],
                          ("sealed-wrong-key", "bundle-sealed", wrong, False),
                          ("user-key", "bundle", out / "user.key", False),
                          ("sealed-user-key", "bundle-sealed", out / "user.key", False)]  # fmt: skip
            if not user_key:
                conditions = [c for c in conditions if not c[0].endswith("user-key")]
            for name, bundle, key, encoder in conditions:
                info = out / t / p / "lerobot-eval" / name / "eval_info.json"
                if info.is_file():
                    continue
                shutil.rmtree(info.parent, ignore_errors=True)
                t0 = time.perf_counter()
                run(lerobot_eval_command(out, t, p, name, bundle, key, LEROBOT_EVAL_EPISODES, encoder),
                    log=out / t / p / f"lerobot-eval-{name}.log")  # fmt: skip
                r = json.loads(info.read_text())
                print(f"lerobot-eval {t} {p} {name}: pc_success {r['overall']['pc_success']:.1f} "
                      f"({time.perf_counter() - t0:.0f} s)", flush=True)  # fmt: skip
