"""Personalize the IL and digits examples with defaults, then run the default audit on each.

    python -m examples.audit_il_digits OUT_DIR [--seed N] [--only il|digits]

Per task: write the example (base checkpoint + user data), `prop keygen`, `prop personalize` with
defaults, `prop attack` with defaults (every probe in the registry: null, 4096 random keys, Hamming
1..8 x 256, 1M streamed black-box keys, encoder structure, T1 relaxed search with 128 restarts, T2,
T3 few-shot) plus a key that is no user of the bundle (audited as a plain key, with a warning),
`--original` for the searches' controls and `--max-leak 0.05`; prints the decision, the table, each
row's bundle / control / beyond, the audit's wall and CPU time (the issue's goal: <= 60 s on 2 cores
for IL) and the black-box scan's throughput, and writes OUT_DIR/<task>/audit.json and audit.png.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import time
from pathlib import Path


def _prop(*args: str, quiet: bool = False) -> int:
    done = subprocess.run(["prop", *map(str, args)], stdout=subprocess.DEVNULL if quiet else None)
    return done.returncode


def run_task(task: str, out_dir: Path, seed: int) -> dict:
    if task == "il":
        from examples.il_task import write_example
    else:
        from examples.digits_task import write_example
    d = out_dir / task
    paths = write_example(d, seed=seed)
    for k in ("k.bin", "other.bin"):
        if not (d / k).exists():
            _prop("keygen", d / k, quiet=True)
    bundle = d / "mine.prop"
    t0 = time.perf_counter()
    rc = _prop("personalize", paths["base"], "--data", paths["mine"], "--key-file", d / "k.bin",
               "--out", bundle, "--device", "cpu", "--seed", seed, "--force", quiet=True)  # fmt: skip
    if rc:
        raise SystemExit(f"prop personalize failed for {task} (exit {rc})")
    t_pers = time.perf_counter() - t0
    t0 = time.perf_counter()
    cpu0 = _child_cpu()
    # The user audits on their own data; other.bin was never trained (a plain key row, with a warning).
    rc = _prop("attack", bundle, "--data", paths["mine"], "--key-file", d / "k.bin", "--key-file",
               d / "other.bin", "--original", paths["base"], "--json", d / "audit.json",
               "--plot", d / "audit.png", "--max-leak", "0.05", "--force")  # fmt: skip
    t_audit, cpu_audit = time.perf_counter() - t0, _child_cpu() - cpu0
    if rc not in (0, 1):
        raise SystemExit(f"prop attack failed for {task} (exit {rc})")
    report = json.loads((d / "audit.json").read_text())
    print(f"{task}: personalize {t_pers:.1f} s; audit {t_audit:.1f} s wall, {cpu_audit:.1f} s CPU "
          f"(user + system, all threads; wall = CPU on an idle machine)\n")  # fmt: skip
    return report


def _child_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _rows(task: str, rep: dict) -> None:
    print(f"{task}: {rep['max_leak']['verdict']}")
    print(f"{task}: per row, worst leakage on the bundle / the control / beyond, and what --max-leak gates")
    for g in rep["groups"]:
        c = g["control"]
        ctrl = f"{c['leakage']['worst']:.3f}" if c and c.get("available") else "n/a"
        beyond = "" if g["beyond"] is None else f"{g['beyond']:.3f}"
        print(f"  {g['threat']:10s} {g['name']:17s} {g['leakage']['worst']:.3f}  {ctrl:>5s}  {beyond:>5s}  "
              f"gate {g['gate']['on']}")  # fmt: skip
    bb = rep["speed"].get("blackbox")
    if bb:
        print(f"  blackbox scan: {bb['scanned']} keys x {bb['screen_samples']} samples, "
              f"{bb['evaluations_per_second'] / 1e6:.2f}M evaluations/s wall, "
              f"{bb['evaluations_per_cpu_second'] / 1e6:.2f}M per CPU-second ({bb['path']})")  # fmt: skip


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m examples.audit_il_digits", description=__doc__)
    ap.add_argument("out_dir", type=Path)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", choices=["il", "digits"], default=None)
    args = ap.parse_args(argv)
    for task in [args.only] if args.only else ["il", "digits"]:
        rep = run_task(task, args.out_dir, args.seed)
        _rows(task, rep)
        srch = {
            g["name"]: g["search"] for g in rep["groups"] if g.get("search") and "restarts" in g["search"]
        }
        for name, s in srch.items():
            dist = (
                f", code distance to the user's code per restart {s['code_distance']}"
                if "code_distance" in s
                else ""
            )
            print(f"{task} {name}: search pick leakage {s['best_leakage']:.4f}, per restart "
                  f"{[round(v, 3) for v in s['leakage']]}{dist}")  # fmt: skip
        print()


if __name__ == "__main__":
    main()
