"""Speed of `prop attack` on the IL example's MLP (4-192-192-2): key x sample evaluations per second
and the default audit's wall time (null, 4096 random, 1..8 x 256 neighbours, 8 restarts x 200 steps
of each search, 256 samples).

    OMP_NUM_THREADS=2 python -m benchmarks.bench_attack [--workdir DIR] [--threads 1,2]

Goals (issue 3): >= 1,000,000 evaluations/s on 2 cores; the default audit under 60 s. Issue 40: the
audit's key probe >= 10M evaluations/s; the "keyed matmuls alone" lines are the most any exact key probe
reaches on these threads.
Timings on a shared machine are noisy: each figure is the best of --repeat runs.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch


def prepare(workdir: Path) -> tuple[Path, Path, Path]:
    """IL example + key + a default `prop personalize` run (reused when already there)."""
    from examples.il_task import write_example

    bundle, key = workdir / "il.prop", workdir / "k.bin"
    if not (workdir / "mine.npz").exists():
        write_example(workdir)
    if not key.exists():
        key.write_bytes(os.urandom(16))
        key.chmod(0o600)
    if not bundle.exists():
        cmd = ["prop", "personalize", str(workdir / "base.safetensors"), "--data", str(workdir / "mine.npz"),
               "--key-file", str(key), "--out", str(bundle), "--device", "cpu"]  # fmt: skip
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return bundle, workdir / "mine.npz", key


def throughput(bundle: Path, data: Path, keys: int, samples: int, repeat: int) -> dict[str, float]:
    from prop_cli.attack.probes.screen import ChainKeys
    from prop_cli.bundle import load_bundle
    from prop_cli.core.keyed_model import key_codes, keys_per_forward

    km = load_bundle(bundle).keyed
    x = torch.from_numpy(np.load(data)["x"][:samples])
    codes = key_codes(np.random.default_rng(0).integers(0, 2, (keys, 128), dtype=np.uint8), "hashed")
    per = keys_per_forward(samples)

    def rows(x: torch.Tensor, deltas: list[torch.Tensor]) -> torch.Tensor:
        # The per-row path: one delta row per (key, sample) row, prefix gathered by sample index.
        k, b = deltas[0].shape[0], x.shape[0]
        return km.run_rows(x, deltas, torch.arange(k).repeat_interleave(b), torch.arange(b).repeat(k))

    out = {}
    with torch.inference_mode():
        deltas = km.layer_deltas(codes)
        fast = ChainKeys(km, x)
        paths = (("run_keys (broadcast)", km.run_keys), ("run_rows (row per key x sample)", rows),
                 ("ChainKeys (the key probes')", lambda x, deltas: fast(deltas)))  # fmt: skip
        for name, fn in paths:
            best = float("inf")
            for _ in range(repeat):
                t0 = time.perf_counter()
                for i in range(0, keys, per):
                    fn(x, [d[i : i + per] for d in deltas])
                best = min(best, time.perf_counter() - t0)
            out[name] = keys * samples / best
        out.update(ceiling(km, len(x) * per, repeat))
    return out


def ceiling(km, rows: int, repeat: int) -> dict[str, float]:
    """What the keyed layers' matmuls alone allow (issue 40: the key probe's goal of 10M evaluations/s):
    ``rows`` (key, sample) rows through every keyed layer's weight, fp32 and bf16, no hook, no
    activation, no encoder. Key x sample evaluations per second: no probe that scores exact outputs
    runs faster on these threads."""
    mods = dict(km.module.named_modules())
    weights = [mods[n].weight.detach() for n in km.layer_names]
    out = {}
    for dtype in (torch.float32, torch.bfloat16):
        ws = [w.to(dtype).T.contiguous() for w in weights]
        zs = [torch.randn(rows, w.shape[0], dtype=dtype) for w in ws]
        best = float("inf")
        for _ in range(repeat + 1):  # the first: a warm-up
            t0 = time.perf_counter()
            for z, w in zip(zs, ws):
                z @ w
            best = min(best, time.perf_counter() - t0)
        out[f"keyed matmuls alone, {str(dtype).removeprefix('torch.')}"] = rows / best
    return out


def default_audit(bundle: Path, data: Path, key: Path) -> dict:
    from prop_cli.attack.audit import audit
    from prop_cli.bundle import load_bundle
    from prop_cli.config import AuditSettings
    from prop_cli.core.key_files import read_key_file
    from prop_cli.datasources import load_data

    b = load_bundle(bundle)
    return audit(b, load_data(data), [read_key_file(key, b.key_bits)], AuditSettings())


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.bench_attack", description=__doc__)
    ap.add_argument("--workdir", type=Path, default=None, help="reuse an IL example + bundle here")
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("--keys", type=int, default=4096)
    ap.add_argument("--samples", type=int, default=256)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="bench_attack."))
    workdir.mkdir(parents=True, exist_ok=True)
    bundle, data, key = prepare(workdir)
    print(f"IL bundle {bundle}; cpu count {os.cpu_count()}; load {os.getloadavg()[0]:.2f}")
    for threads in (int(t) for t in args.threads.split(",")):
        torch.set_num_threads(threads)
        for name, rate in throughput(bundle, data, args.keys, args.samples, args.repeat).items():
            print(f"threads {threads}: {name:28s} {rate / 1e6:6.2f} M key x sample evaluations/s")
        rep = default_audit(bundle, data, key)
        sp = rep["speed"]
        st, n = rep["settings"], rep["data"]["samples"]
        rate = st["random"] * n / sp["stage_seconds"]["random"]
        what = f"(T0 random: {st['random']} keys x {n} samples, its control included; goal 10 M/s)"
        print(f"threads {threads}: {'key probe in the audit':28s} {rate / 1e6:6.2f} M evaluations/s {what}")
        stages = ", ".join(f"{k} {v:.1f}s" for k, v in sp["stage_seconds"].items())
        print(
            f"threads {threads}: default audit {sp['wall_seconds']:.1f} s wall "
            f"({sp['key_sample_evaluations']:,} probe evaluations at "
            f"{sp['evaluations_per_second'] / 1e6:.2f} M/s; {stages})"
        )
    sys.stdout.flush()


if __name__ == "__main__":
    main()
