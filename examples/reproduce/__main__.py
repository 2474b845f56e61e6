"""python -m examples.reproduce il|digits|reach|capacity|kitchen|all [--quick] [--seeds N] [--out DIR]
                                [--mnist DIR] [--max-users N] [--per-participant] [--workers N]

Prints a Fig.-4-style table per experiment (markdown) and writes, under --out (default out/reproduce):
<name>.md, <name>.png and <name>.json (per-seed values). Seeds are fixed: a rerun gives the same table.
Threads follow prop's policy (prop_cli.threads: one thread for these small models); OMP_NUM_THREADS wins.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

EXPERIMENTS = ("il", "digits", "capacity", "reach", "kitchen")


def run_experiment(
    name: str,
    out: Path,
    quick: bool,
    seeds: int | None,
    mnist: Path | None,
    log,
    max_users: int | None = None,
    per_participant: bool = False,
    workers: int | None = None,
) -> list[dict]:
    """Run one experiment; returns its result dicts (one per table) after writing md/png/json."""
    from examples.reproduce import table

    t0 = time.perf_counter()
    if name == "il":
        from examples.reproduce import il

        results = il.run(out, quick, seeds, log=log)
    elif name == "digits":
        from examples.reproduce import digits

        results = digits.run(out, quick, seeds, mnist=mnist, log=log)
    elif name == "capacity":
        from examples.reproduce import capacity

        sweep = capacity.USERS_QUICK if quick else capacity.USERS_FULL
        users = [n for n in sweep if max_users is None or n <= max_users] or [1]
        results = capacity.run(out, quick, mnist=mnist, log=log, users=tuple(users))
    elif name == "kitchen":
        from examples.reproduce import kitchen

        results = kitchen.run(
            out, quick, seeds, log=log, max_users=max_users, per_participant=per_participant, workers=workers
        )
    else:
        from examples.reproduce import reach

        results = reach.run(out, quick, seeds, log=log)
    wall = time.perf_counter() - t0
    for r in results:
        r["wall_seconds_experiment"] = wall
        text = r["markdown"] if "markdown" in r else table.markdown(r)
        (out / f"{r['name']}.md").write_text(text + "\n")
        png = r.get("png") or table.plot(r, out / f"{r['name']}.png")
        (out / f"{r['name']}.json").write_text(
            json.dumps({k: v for k, v in r.items() if k != "markdown"}, indent=1, default=str)
        )
        print(text)
        print(f"\n({r['name']}: table {out / (r['name'] + '.md')}, figure {png})\n")
    print(f"{name}: wall time {wall:.1f} s", file=sys.stderr)
    return results


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m examples.reproduce", description=__doc__)
    ap.add_argument("experiment", choices=[*EXPERIMENTS, "all"])
    ap.add_argument("--quick", action="store_true", help="tiny smoke version (each in under a minute)")
    ap.add_argument(
        "--seeds", type=int, default=None, help="seeds (kitchen: repetitions); default: per experiment"
    )
    ap.add_argument("--out", type=Path, default=Path("out/reproduce"))
    ap.add_argument(
        "--mnist", type=Path, default=None, help="folder with local MNIST idx files (no download)"
    )
    ap.add_argument("--max-users", type=int, default=None, help="capacity, kitchen: cap the user sweep")
    ap.add_argument(
        "--per-participant",
        action="store_true",
        help="kitchen: one bundle per participant (the paper's protocol; ~12x the training time)",
    )
    ap.add_argument(
        "--workers", type=int, default=None, help="kitchen: processes over repetitions (default 2; --quick 1)"
    )
    ap.add_argument("--keep-work", action="store_true", help="keep the bundles and data under OUT/work")
    args = ap.parse_args(argv)

    from prop_cli.errors import PropError
    from prop_cli.threads import configure

    # The bases, baselines and PRoP runs here are all small models: prop's thread policy for them
    # (one thread unless OMP_NUM_THREADS says otherwise), set before the first of them trains.
    configure(parameters=0)

    args.out.mkdir(parents=True, exist_ok=True)
    names = EXPERIMENTS if args.experiment == "all" else (args.experiment,)

    def log(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    failed = []
    for name in names:
        try:
            run_experiment(
                name,
                args.out,
                args.quick,
                args.seeds,
                args.mnist,
                log,
                args.max_users,
                args.per_participant,
                args.workers,
            )
        except PropError as e:
            print(f"reproduce {name}: error: {e.line()}", file=sys.stderr)
            failed.append(name)
    if not args.keep_work:
        shutil.rmtree(args.out / "work", ignore_errors=True)
    return 2 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
