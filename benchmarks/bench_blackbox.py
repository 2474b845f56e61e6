"""Throughput of the audit's black-box scan (``blackbox`` probe) on the IL example's MLP (4-192-192-2).

    python -m benchmarks.bench_blackbox [--workdir DIR] [--keys 200000] [--screen 8,32]

Per screening size S: the streamed scan (``ProbeContext.probe_keys_stream``: keys, SHAKE-256 codes,
encoder in bf16, the bf16 chain forward, screening, top-k) in key x sample evaluations per second of
wall time and per CPU-second (all threads; the key hashing runs on a second thread), with where the
time goes; and, in the same run, the model forward alone: the bf16 chain against ``run_keys`` in fp32
(the ratio is the figure to compare across machines). Goal (issue 13): >= 10M evaluations/s on 2 cores.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.bench_blackbox", description=__doc__)
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/prop_bench_blackbox"))
    ap.add_argument("--keys", type=int, default=200_000)
    ap.add_argument("--screen", default="8,32")
    args = ap.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import numpy as np
    import torch

    torch.set_num_threads(1)
    from benchmarks.bench_attack import prepare
    from prop_cli.bundle import load_bundle
    from prop_cli.config import AuditSettings
    from prop_cli.keys import read_key_file
    from prop_cli.probes.base import ProbeContext, Reference
    from prop_cli.probes.blackbox import CHUNK
    from prop_cli.probes.screen import ChainForward

    args.workdir.mkdir(parents=True, exist_ok=True)
    bundle_path, data, key_path = prepare(args.workdir)
    bundle = load_bundle(bundle_path)
    km = bundle.keyed.eval().requires_grad_(False)
    d = np.load(data)
    x = torch.from_numpy(d["x"][:256])
    with torch.inference_mode():
        b = km.module(x)
    ref = Reference(x, b.clone(), torch.from_numpy(d["y"][:256]), bundle.task)
    key = read_key_file(key_path, bundle.key_bits)
    ctx = ProbeContext(km, ref, AuditSettings(), [key], bundle.key_encoding, probe="bench")
    print(f"IL bundle {bundle_path}; cpu count {os.cpu_count()}; load {os.getloadavg()[0]:.2f}; "
          f"torch threads {torch.get_num_threads()}")  # fmt: skip

    rng = np.random.default_rng(0)
    bits = rng.integers(0, 2, (CHUNK, bundle.key_bits), dtype=np.uint8)
    with torch.inference_mode():
        deltas = ctx.key_deltas(bits)
        for s in [int(v) for v in args.screen.split(",")]:
            fast = ChainForward(km, x[:s])
            rates = {}
            xs = x[:s]
            for name, fn in (
                ("bf16 chain", lambda f=fast: f(deltas)),
                ("run_keys fp32", lambda xs=xs: km.run_keys(xs, deltas)),
            ):
                fn()
                t0, c0, n = time.perf_counter(), time.process_time(), 0
                while time.perf_counter() - t0 < 1.0:
                    fn()
                    n += 1
                rates[name] = (
                    CHUNK * s * n / (time.perf_counter() - t0),
                    CHUNK * s * n / (time.process_time() - c0),
                )
            (fw, fc), (sw, sc) = rates["bf16 chain"], rates["run_keys fp32"]
            print(f"model forward alone, S={s}: bf16 chain {fw / 1e6:.2f}M/s wall "
                  f"({fc / 1e6:.2f}M per CPU-s), run_keys fp32 {sw / 1e6:.2f}M/s "
                  f"({sc / 1e6:.2f}M per CPU-s): ratio {fw / sw:.2f}x")  # fmt: skip

    for s in [int(v) for v in args.screen.split(",")]:
        chunks = (rng.integers(0, 2, (min(CHUNK, args.keys - i), bundle.key_bits), dtype=np.uint8)
                  for i in range(0, args.keys, CHUNK))  # fmt: skip
        scan = ctx.probe_keys_stream(chunks, args.keys, "bench", screen=s, keep=256)
        wall, cpu = scan.seconds["scan"], scan.seconds["scan_cpu"]
        evals = scan.scanned * s
        parts = ", ".join(f"{k} {v:.2f} s" for k, v in scan.seconds.items())
        print(f"scan S={s}: {scan.scanned:,} keys in {wall:.2f} s wall / {cpu:.2f} s CPU: "
              f"{scan.scanned / wall / 1e3:.0f}k keys/s, {evals / wall / 1e6:.2f}M evaluations/s wall, "
              f"{evals / cpu / 1e6:.2f}M per CPU-second ({scan.path}; {parts})")  # fmt: skip


if __name__ == "__main__":
    main()
