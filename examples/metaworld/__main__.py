"""MetaWorld through LeRobot's own environment: record, train, personalize, judge (figures in
examples/RESULTS.md, "MetaWorld, judged by lerobot-eval").

    bash scripts/setup-lerobot.sh   # then lerobot[metaworld]==0.6.1 and mujoco 3.3.2 (README there)
    export MUJOCO_GL=egl OMP_NUM_THREADS=1
    .venv-lerobot/bin/python -m examples.metaworld record --out out/metaworld
    .venv-lerobot/bin/python -m examples.metaworld train --out out/metaworld
    .venv-lerobot/bin/python -m examples.metaworld personalize --out out/metaworld
    .venv-lerobot/bin/python -m examples.metaworld judge --out out/metaworld
    .venv-lerobot/bin/python -m examples.metaworld lerobot-eval --out out/metaworld
    .venv-lerobot/bin/python -m examples.metaworld table --out out/metaworld
    .venv-lerobot/bin/python -m examples.metaworld all --out out/metaworld

Each step skips what the run folder already holds (a dataset, a checkpoint, a bundle, a judged
condition), so a stopped run continues where it stopped. Layout of --out, per task T and policy P:
T/base, T/user (LeRobotDatasets), T/P/train (lerobot-train's output; the policy in
checkpoints/last/pretrained_model), user.key, T/P/bundle, T/P/bundle-sealed, T/P/judge/*.json.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from examples.metaworld import task as mw

BASE_EPISODES, USER_EPISODES = 40, 15
BASE_SEED, USER_SEED = 0, 50_000


def step_record(out: Path, tasks: list[str], base_episodes: int, user_episodes: int) -> None:
    for t in tasks:
        for name, n, seed, offset in (("base", base_episodes, BASE_SEED, None),
                                      ("user", user_episodes, USER_SEED, mw.user_offset(t))):  # fmt: skip
            root = out / t / name
            done = root / "record.json"
            if done.is_file():
                print(f"record: {root} done ({json.loads(done.read_text())['episodes']} episodes)")
                continue
            if root.exists():
                import shutil

                shutil.rmtree(root)
            t0 = time.perf_counter()
            counts = mw.record(root, t, n, seed, offset)
            counts["seconds"] = round(time.perf_counter() - t0, 1)
            done.write_text(json.dumps(counts, indent=1))
            print(f"record: {root}: {counts['episodes']} episodes, {counts['frames']} frames, MetaWorld "
                  f"success {counts['success']}, user's criterion {counts['user_success']} "
                  f"({counts['seconds']} s)", flush=True)  # fmt: skip


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m examples.metaworld", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    ap.add_argument(
        "step", choices=("record", "train", "personalize", "judge", "lerobot-eval", "table", "all")
    )
    ap.add_argument("--out", type=Path, default=Path("out/metaworld"))
    ap.add_argument("--tasks", default=mw.TASKS[0], help=f"comma-separated (chosen: {', '.join(mw.TASKS)})")
    ap.add_argument("--policies", default="act", help="comma-separated: act, diffusion")
    ap.add_argument("--base-episodes", type=int, default=BASE_EPISODES)
    ap.add_argument("--user-episodes", type=int, default=USER_EPISODES)
    ap.add_argument(
        "--no-user-key", action="store_true",
        help="lerobot-eval: leave out the user's key (its episodes can run LeRobot's whole 500 steps)",
    )  # fmt: skip
    args = ap.parse_args(argv)
    tasks = [t.strip() for t in args.tasks.split(",") if t.strip()]
    if args.step in ("record", "all"):
        step_record(args.out, tasks, args.base_episodes, args.user_episodes)
    if args.step in ("train", "personalize", "judge", "lerobot-eval", "table", "all"):
        from examples.metaworld import pipeline

        policies = [p.strip() for p in args.policies.split(",") if p.strip()]
        for step in ("train", "personalize", "judge", "lerobot-eval", "table"):
            if args.step in (step, "all"):
                extra = {"user_key": not args.no_user_key} if step == "lerobot-eval" else {}
                getattr(pipeline, f"step_{step.replace('-', '_')}")(args.out, tasks, policies, **extra)


if __name__ == "__main__":
    sys.exit(main())
