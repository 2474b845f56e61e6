"""How long `prop --help` (and one command's --help) takes, as users start it: a fresh process each time.

    python -m benchmarks.bench_cli [--reps 15]

Prints the median wall time of the `prop` entry point next to a bare `python -c pass` measured in the
same run (the interpreter's own start-up), alternating the two so machine load hits both alike. The
target (issue 19) is under 0.5 s for `prop --help`.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import subprocess
import sys
import time


def _time(cmd: list[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True)
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reps", type=int, default=15)
    args = ap.parse_args(argv)
    prop = shutil.which("prop")
    entry = [prop] if prop else [sys.executable, "-m", "prop_cli.cli.main"]
    cases = {
        "python -c pass": [sys.executable, "-c", "pass"],
        "prop --help": [*entry, "--help"],
        "prop personalize --help": [*entry, "personalize", "--help"],
    }
    times: dict[str, list[float]] = {k: [] for k in cases}
    for _ in range(args.reps):
        for name, cmd in cases.items():
            times[name].append(_time(cmd))
    base = statistics.median(times["python -c pass"])
    print(f"{'command':28s} {'median s':>9s} {'vs python':>10s}")
    for name, t in times.items():
        m = statistics.median(t)
        print(f"{name:28s} {m:9.3f} {m / base:9.1f}x")


if __name__ == "__main__":
    main()
