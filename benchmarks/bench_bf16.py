"""bf16 frozen weights (issue 40): `prop personalize` unsealed and --seal, fp32 against --precision bf16,
on a bf16 checkpoint, each run in its own process (``bench_real_size``'s runs and figures).

    bash scripts/setup-lerobot.sh
    .venv-lerobot/bin/python -m benchmarks.bench_bf16 [--policies pi0,smolvla] [--steps 3] [--real-size]

Without ``--real-size`` the policies are the tiny ones the tests build (examples/pi_tiny.py,
examples/smolvla_tiny.py); with it, their published sizes (bench_real_size's builds: pi0 4 B
parameters, up to about 20 GiB of memory and most of an hour per run on 2 cores, docs/speed.md).
pi0's checkpoint is written as lerobot/pi0_base holds it (bf16, the vision tower, projector and norms
fp32); SmolVLA's, built fp32, is rewritten bf16 first (every float tensor): both are bf16 checkpoints.

The unsealed run (bench_real_size's ``prop``) takes ``--freeze-base``: LeRobot's pi0 trains every
weight by default, so without it nothing is frozen and there is nothing to hold bf16 (SmolVLA's own
``train_expert_only`` freezes its VLM either way).

``--load-only``: the load alone, each its own process: the checkpoint loaded as ``prop personalize``
loads it at fp32 (every weight fp32) and at ``--precision bf16`` (each weight in the checkpoint's own
dtype, ``CheckpointOptions.keep_dtypes``), its peak resident memory and the weights' bytes.

Printed per policy and run: peak resident memory, the largest sampled in the steps, the median step,
the bundle's base file beside the checkpoint's and beside the fp32 base prop wrote before issue 40
(4 bytes per float value, computed from the checkpoint's header), then bf16 / fp32 ratios. The
command line comes first.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shlex
import subprocess
import sys
import tempfile
from pathlib import Path

from benchmarks.bench_real_size import TINY_ENV, build, median, tiny_pi

MIB = 2**20
TINY_IMAGE = {"pi0": 32, "smolvla": 64}  # the tiny builds' camera frames (pi0: pi_tiny.IMAGE)
EPISODES, FRAMES = 4, 5  # bench_real_size's defaults


def fp32_size(path: Path) -> int:
    """The bytes of ``path``'s tensors with every float one held fp32 (prop's base before issue 40)."""
    from safetensors import safe_open

    total = 0
    with safe_open(str(path), framework="pt", device="cpu") as f:
        for name in f.keys():
            s = f.get_slice(name)
            n = 1
            for d in s.get_shape():
                n *= d
            dt = s.get_dtype()
            total += n * (4 if dt in ("F16", "BF16", "F32") else {"F64": 8, "I64": 8, "I32": 4}.get(dt, 1))
    return total


def to_bf16(path: Path) -> None:
    import torch
    from safetensors import safe_open
    from safetensors.torch import save_file

    with safe_open(str(path), framework="pt", device="cpu") as f:
        meta = f.metadata()
        tensors = {n: f.get_tensor(n) for n in f.keys()}
    tensors = {n: t.to(torch.bfloat16) if t.is_floating_point() else t for n, t in tensors.items()}
    save_file(tensors, str(path), metadata=meta)


def load_worker(folder: str, precision: str) -> None:
    """Load ``folder`` as personalize does at ``precision``; print its figures as one JSON line."""
    import resource
    import time

    from prop_adapters import CheckpointOptions, load_checkpoint

    t = time.perf_counter()
    with tiny_pi() if os.environ.get(TINY_ENV) else contextlib.nullcontext():  # the tiny pi0's sizes
        loaded = load_checkpoint(folder, CheckpointOptions(keep_dtypes=precision == "bf16"))
    params = list(loaded.module.parameters())
    print(json.dumps({
        "load_s": time.perf_counter() - t,
        "rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
        "weights_gib": sum(p.numel() * p.element_size() for p in params) / 2**30,
        "dtypes": sorted({str(p.dtype).removeprefix("torch.") for p in params}),
    }))  # fmt: skip


def load_only(policies: list[str], work: Path, real_size: bool, env: dict) -> None:
    print("| policy | precision | peak memory | weights | dtypes | load |")
    print("|---|---|---|---|---|---|")
    peaks = {}
    for policy in policies:
        folder = work / policy / (f"{policy}-tiny" if not real_size else policy)
        for precision in ("fp32", "bf16"):
            cmd = [sys.executable, "-m", "benchmarks.bench_bf16", "worker-load", str(folder), precision]
            done = subprocess.run(cmd, check=True, env=env, capture_output=True, text=True)
            r = json.loads(done.stdout.strip().splitlines()[-1])
            peaks[policy, precision] = r["rss_gib"]
            print(f"| {policy} | {precision} | {r['rss_gib']:.2f} GiB | {r['weights_gib']:.2f} GiB | "
                  f"{', '.join(r['dtypes'])} | {r['load_s']:.0f} s |")  # fmt: skip
    print()
    for policy in policies:
        print(f"{policy}: the load's peak memory, bf16 / fp32: "
              f"{peaks[policy, 'bf16'] / peaks[policy, 'fp32']:.2f}x")  # fmt: skip


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["worker-load"]:
        load_worker(*argv[1:3])
        return
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--policies", default="pi0,smolvla")
    ap.add_argument("--steps", type=int, default=3)
    ap.add_argument("--runs", default="prop,sealed", help="bench_real_size's prop (unsealed) and sealed")
    ap.add_argument("--real-size", action="store_true", help="the published sizes, not the tiny builds")
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--bench-args", default="", help="more bench_real_size flags, quoted")
    ap.add_argument("--load-only", action="store_true", help="the load's peak alone, fp32 against bf16")
    ap.add_argument(
        "--prop-args",
        default="--report-budget 25",
        help="more `prop personalize` flags, quoted (default: a short report; it is not timed)",
    )
    args = ap.parse_args(argv)
    print("command:", shlex.join([Path(sys.executable).name, "-m", "benchmarks.bench_bf16", *argv]))
    work = args.work or Path(tempfile.mkdtemp(prefix="prop-bf16-"))
    env = os.environ | ({} if args.real_size else {TINY_ENV: "1"})
    rows = []
    policies = [p.strip() for p in args.policies.split(",") if p.strip()]
    for policy in policies:
        pw = work / policy
        folder = pw / (f"{policy}-tiny" if not args.real_size else policy)
        base = [sys.executable, "-m", "benchmarks.bench_real_size", "--policy", policy, "--work", str(pw),
                "--steps", str(args.steps), *shlex.split(args.bench_args)]  # fmt: skip
        if not args.real_size:  # the tiny builds take small frames (pi0: pi_tiny.IMAGE)
            base += ["--image", str(TINY_IMAGE[policy])]
        if policy == "smolvla":  # built fp32 (bench_real_size.build, as its runs would), then rewritten bf16
            image = 512 if args.real_size else TINY_IMAGE[policy]
            build(pw, image, EPISODES, FRAMES, tiny=not args.real_size)
            if not (folder / ".bf16").exists():
                to_bf16(folder / "model.safetensors")
                (folder / ".bf16").touch()
        ckpt = folder / "model.safetensors"
        if args.load_only:  # pi0's folder is built by a run (bench_real_size's build_pi0) before
            continue
        for precision in ("fp32", "bf16"):
            for run in [r.strip() for r in args.runs.split(",") if r.strip()]:
                flags = f"--precision {precision} {args.prop_args}" + (
                    " --freeze-base" if run == "prop" else ""
                )
                subprocess.run([*base, "--runs", run, "--prop-args", flags], check=True, env=env,
                               stdout=subprocess.DEVNULL)  # fmt: skip
                r = json.loads((pw / "results.json").read_text())[run]
                bundle = pw / ("unsealed.prop" if run == "prop" else "sealed.prop") / "base.safetensors"
                rows.append(dict(policy=policy, run="unsealed" if run == "prop" else run, precision=precision,
                                 rss=r["rss_gb"], steps_rss=r.get("steps_rss_gib", float("nan")),
                                 step=median(r.get("steps_s", [])), base=bundle.stat().st_size / MIB,
                                 ckpt=ckpt.stat().st_size / MIB, before=fp32_size(ckpt) / MIB))  # fmt: skip
    if args.load_only:
        load_only(policies, work, args.real_size, env)
        return
    print(
        "| policy | run | precision | peak memory | in the steps | step (median) | bundle base | "
        "checkpoint | fp32 base (before) |"
    )
    print("|" + "---|" * 9)
    for r in rows:
        print(
            f"| {r['policy']} | {r['run']} | {r['precision']} | {r['rss']:.2f} GiB | "
            f"{r['steps_rss']:.2f} GiB | {r['step']:.3f} s | {r['base']:.1f} MiB | {r['ckpt']:.1f} MiB | "
            f"{r['before']:.1f} MiB |"
        )
    print()
    for a in rows:
        if a["precision"] != "bf16":
            continue
        b = next(
            r for r in rows if r["precision"] == "fp32" and (r["policy"], r["run"]) == (a["policy"], a["run"])
        )
        print(f"{a['policy']} {a['run']}, bf16 / fp32: peak memory {a['rss'] / b['rss']:.2f}x, in the steps "
              f"{a['steps_rss'] / b['steps_rss']:.2f}x, step {a['step'] / b['step']:.2f}x; bundle base "
              f"{a['base'] / a['before']:.2f}x the fp32 base before issue 40")  # fmt: skip


if __name__ == "__main__":
    main()
