"""The point-mass Diffusion tasks of issue 43: record, train (lerobot-train), personalize (prop
personalize), judge (original, no key, the user's key, 16 random and 16 neighbour wrong keys through the
encoder, paired seeds), drift (per denoising step, a wrong key's noise prediction against the original's),
table. ``--task``: reach (task.py: image and state, the user stops 0.3 to the right of the goal, success
under 0.05), waypoint (task_waypoint.py: image and state, the user comes down onto the goal from above,
success under 0.1) or slow (task_slow.py: state only, the user moves at 0.4 of full speed, success under
0.15); one --out per task (out/task.json names it).

    export MUJOCO_GL=egl OMP_NUM_THREADS=1 HF_HUB_OFFLINE=1
    .venv-lerobot/bin/python -m examples.pointmass_diffusion all --out out/pointmass
    .venv-lerobot/bin/python -m examples.pointmass_diffusion table --out out/pointmass

Each step skips what --out already holds (a dataset, the checkpoint, a bundle, a judged condition), so a
stopped run continues where it stopped. ``--variant NAME --personalize-flags '...'`` personalizes and
judges a second bundle (out/bundle-NAME, out/judge-NAME) from the same checkpoint. ``judge --seed-offset N
--episodes M`` judges every condition on M further seeds (JUDGE_SEED + N ...; out/judge[-NAME]/offset-N);
``table --seed-offset 0 --seed-offset N`` pools blocks of seeds (default: the first block alone).
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

from examples.pointmass_diffusion import world

STEPS = ("record", "train", "personalize", "judge", "drift", "table")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(
        prog="python -m examples.pointmass_diffusion",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("step", choices=(*STEPS, "all"))
    ap.add_argument("--task", choices=sorted(world.TASKS), default="reach")
    ap.add_argument("--out", type=Path, default=None, help="default out/pointmass (reach), out/pm-TASK")
    ap.add_argument("--variant", default="", help="a second bundle's name (bundle-NAME, judge-NAME)")
    ap.add_argument("--personalize-flags", default="", help="extra prop personalize flags for --variant")
    ap.add_argument(
        "--threshold",
        type=float,
        action="append",
        help="table: success as final distance under this (repeatable)",
    )
    ap.add_argument("--episodes", type=int, default=None, help="episodes per condition (default 20)")
    ap.add_argument(
        "--seed-offset",
        type=int,
        action="append",
        help="judge: the first seed's offset from the judge's first (default 0); table: a block of judged "
        "seeds to read (repeatable: pooled; default 0)",
    )
    args = ap.parse_args(argv)
    offsets = args.seed_offset or [0]
    if any(o < 0 for o in offsets):
        ap.exit(2, f"prop: error: --seed-offset {min(offsets)}: an offset is 0 or more\n")
    if args.step in ("judge", "all") and len(offsets) > 1:
        ap.exit(2, "prop: error: --seed-offset: judge takes one block of seeds; pass --seed-offset once\n")
    if len(set(offsets)) < len(offsets):
        ap.exit(2, "prop: error: --seed-offset: a block named twice; pass each offset once\n")
    from examples.pointmass_diffusion import pipeline as p

    t = world.load(args.task)
    if args.out is None:
        args.out = Path("out/pointmass" if args.task == "reach" else f"out/pm-{args.task}")
    p.check_task(args.out, t)

    extra = shlex.split(args.personalize_flags)
    for step in STEPS:
        if args.step not in (step, "all"):
            continue
        if step in ("record", "train"):
            getattr(p, f"step_{step}")(args.out, t)
        elif step == "table":
            p.step_table(args.out, args.threshold, t, offsets)
        elif step == "judge":
            p.step_judge(args.out, args.variant, args.episodes or p.EPISODES, t, offsets[0])
        elif step == "personalize":
            p.step_personalize(args.out, args.variant, extra)
        else:
            p.step_drift(args.out, args.variant, t)


if __name__ == "__main__":
    sys.exit(main())
