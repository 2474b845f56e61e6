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
    ap.add_argument("--bundle", type=Path, help="another bundle (with --data and --key-file)")
    ap.add_argument("--data", type=Path)
    ap.add_argument("--key-file", type=Path)
    ap.add_argument("--recall", type=int, default=0, help="also score N keys exactly: top-10 recall")
    args = ap.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import numpy as np
    import torch

    torch.set_num_threads(1)
    from benchmarks.bench_attack import prepare
    from prop_cli.attack.probes.base import ProbeContext, Reference
    from prop_cli.attack.probes.blackbox import CHUNK
    from prop_cli.attack.probes.screen import ChainForward
    from prop_cli.bundle import load_bundle
    from prop_cli.config import AuditSettings
    from prop_cli.core.key_files import read_key_file

    if args.bundle:
        bundle_path, data, key_path = args.bundle, args.data, args.key_file
    else:
        args.workdir.mkdir(parents=True, exist_ok=True)
        bundle_path, data, key_path = prepare(args.workdir)
    bundle = load_bundle(bundle_path)
    km = bundle.keyed.eval().requires_grad_(False)
    d = np.load(data)
    x = torch.from_numpy(d["x"][:256])
    with torch.inference_mode():
        b = km.module(x)
    y = torch.from_numpy(d["y"][:256])
    ref = Reference(
        x, b.clone(), y[:, None] if bundle.task == "regression" and y.dim() == 1 else y, bundle.task
    )
    key = read_key_file(key_path, bundle.key_bits)
    ctx = ProbeContext(km, ref, AuditSettings(), [key], bundle.key_encoding, probe="bench")
    print(f"bundle {bundle_path}; cpu count {os.cpu_count()}; load {os.getloadavg()[0]:.2f}; "
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

    if args.recall:
        _recall(ctx, args.recall, CHUNK, np)


def _recall(ctx, n: int, chunk: int, np) -> None:
    """Score n keys exactly on every sample and check the screened scan keeps the exact top 10."""
    keys = np.random.default_rng(7).integers(0, 2, (n, ctx.km.encoder.code_bits), dtype=np.uint8)
    exact = ctx.probe_keys(keys, "exact")["leakage"]
    scan = ctx.probe_keys_stream(
        (keys[i : i + chunk] for i in range(0, n, chunk)), n, "scan", screen=8, keep=256
    )
    kept = {k.tobytes() for k in scan.bits}
    top = exact.argsort(descending=True)[:10].numpy()
    hits = sum(keys[i].tobytes() in kept for i in top)
    print(
        f"recall: of the exact top 10 of {n:,} keys by leakage (worst {float(exact.max()):.3f}), the scan "
        f"(S=8, keep 256) kept {hits}; its worst after re-scoring {float(scan.values['leakage'].max()):.3f}"
    )


if __name__ == "__main__":
    main()
