"""One process against 2 CPU processes (`accelerate launch`, gloo) personalizing the same LeRobot policy.

    bash scripts/setup-lerobot.sh
    OMP_NUM_THREADS=1 .venv-lerobot/bin/python -m benchmarks.bench_dist_policies --steps 50

For each policy (the small ACT, Diffusion and SmolVLA of examples/, and pi0 where examples/pi_tiny.py is
there, built here) and mode (unsealed, ``--seal``) it runs `prop personalize` once as one process and
once under `accelerate launch --num_processes 2`, with the same seed, data and key, and prints the
largest difference between the two bundles' trained weights (unsealed: the base and the key encoder;
sealed: the user's payload, opened with the key) and each run's wall time.

Attention key biases (``in_proj_bias``'s middle third, nn.MultiheadAttention: ACT; ``k_proj.bias``:
pi0's SigLIP) are listed apart: softmax is invariant to them (q . b_k shifts every logit of a query
alike), so their true gradient is 0 and what is computed is rounding noise, which Adam turns into steps
of the learning rate's size. They change no output, and two one-process runs with 1 and 2 threads
differ in them as much.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import importlib.util
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

MODES = ("unsealed", "sealed")
# Small rows per step, so that the run is about the split and not the machine.
ROWS = ["--user-rows", "8", "--null-rows", "4", "--neighbour-keys", "2", "--random-keys", "2",
        "--samples-per-key", "1"]  # fmt: skip


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def launch(processes: int, module: str = "prop_cli.cli.main") -> list[str]:
    """The command that starts `prop` (``module``) as ``processes`` CPU processes (gloo); as one process
    without it."""
    if processes == 1:
        return [sys.executable, "-m", module]
    # --multi_gpu: several processes (prop asks Accelerate for gloo on the CPU); --cpu alone starts one.
    return [sys.executable, "-m", "accelerate.commands.launch", "--multi_gpu", "--num_processes",
            str(processes), "--num_machines", "1", "--mixed_precision", "no", "--dynamo_backend", "no",
            "--main_process_port", str(free_port()), "-m", module]  # fmt: skip


def personalize(
    processes: int, policy: Path, data: Path, key: Path, out: Path, steps: int, seal: bool,
    general: Path | None = None, module: str = "prop_cli.cli.main",
) -> tuple[float, dict]:  # fmt: skip
    """Run `prop personalize` as ``processes`` processes; its wall time and its --json report."""
    args = ["personalize", str(policy), "--data", str(data), "--key-file", str(key), "--out", str(out),
            "--steps", str(steps), "--device", "cpu", "--json", *ROWS]  # fmt: skip
    if seal:
        args.append("--seal")
    elif general is not None:
        args += ["--general-data", str(general)]
    env = dict(os.environ, OMP_NUM_THREADS="1", HF_HUB_OFFLINE="1")
    t = time.perf_counter()
    run = subprocess.run([*launch(processes, module), *args], capture_output=True, text=True, env=env)
    if run.returncode != 0:
        raise RuntimeError(f"{processes} process(es) failed:\n{run.stderr[-3000:]}")
    return time.perf_counter() - t, json.loads(run.stdout)


def trained_weights(bundle: Path, key: Path) -> dict[str, np.ndarray]:
    """What training changed: unsealed, the base and the key encoder; sealed, the user's payload."""
    from safetensors.numpy import load_file

    from prop_cli.bundle import load_bundle
    from prop_cli.core.key_files import read_key_file

    if (bundle / "encoder.safetensors").is_file():
        files = {f: load_file(str(bundle / f"{f}.safetensors")) for f in ("base", "encoder")}
        return {f"{f}:{k}": v for f, tensors in files.items() for k, v in tensors.items()}
    opened = load_bundle(bundle).records.open(read_key_file(key))
    return {k: v.numpy() for k, v in opened.payload.tensors().items()}


def key_bias(name: str, v: np.ndarray) -> np.ndarray | None:
    """The entries of an attention's key bias: the middle third of nn.MultiheadAttention's packed q/k/v
    ``in_proj_bias`` (ACT), a transformers attention's ``k_proj.bias`` (SigLIP: pi0's vision tower)."""
    if name.endswith("in_proj_bias"):
        return np.arange(len(v) // 3, 2 * len(v) // 3)
    return np.arange(len(v)) if name.endswith("k_proj.bias") else None


def differences(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> tuple[float, float]:
    """The largest |a - b| over every trained weight but attention key biases, and over those."""
    assert a.keys() == b.keys(), sorted(set(a) ^ set(b))
    rest, keys = 0.0, 0.0
    for k in a:
        d = np.abs(a[k].astype(np.float64) - b[k].astype(np.float64))
        kb = key_bias(k, d)
        if kb is not None:
            keys = max(keys, float(d[kb].max()))
            d = np.delete(d, kb)
        rest = max(rest, float(d.max()) if d.size else 0.0)
    return rest, keys


PI = ("pi0", "pi05")  # built by examples/pi_tiny.py


def build_pi(folder: Path, kind: str) -> None:
    """The camera task's data and a tiny ``kind`` trained on it for 3 LeRobot steps (examples/pi_tiny.py)."""
    from examples import lerobot_reach_task as task
    from examples import pi_tiny

    task.record(folder / "general", 4, 0, np.zeros(3, np.float32), camera=True)
    task.record(folder / "user", 3, 50_000, task.USER_OFFSET, camera=True)
    stats = task.dataset_stats(folder / "general")
    built = pi_tiny.build_pi(kind, pi_tiny.build_tokenizer(folder / "tok"), stats)
    task.train_base(folder / "general", folder / kind, steps=3, built=built)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--policy", nargs="+", default=["act", "diffusion", "smolvla", "pi0"])
    ap.add_argument("--mode", nargs="+", choices=MODES, default=list(MODES))
    ap.add_argument("--keep", type=Path, help="keep the policies, data and bundles here")
    args = ap.parse_args(argv)
    from examples.smolvla_tiny import record_and_build

    work = args.keep or Path(tempfile.mkdtemp(prefix="prop-bench-dist-"))
    work.mkdir(parents=True, exist_ok=True)
    key = work / "k.bin"
    key.write_bytes(np.random.default_rng(0).integers(0, 256, 16, dtype=np.uint8).tobytes())
    key.chmod(0o600)
    print(f"{args.steps} steps, 1 process vs 2 CPU processes (gloo), OMP_NUM_THREADS=1; largest weight "
          "difference (attention key biases apart: see the docstring)")  # fmt: skip
    print(f"{'policy':10} {'mode':9} {'max |1 - 2|':>12} {'key biases':>11} {'1 proc s':>9} "
          f"{'2 procs s':>10}")  # fmt: skip
    for kind in args.policy:
        folder = work / kind
        base = folder / kind
        if kind in PI and importlib.util.find_spec("examples.pi_tiny") is None:
            print(f"{kind:10} skipped: examples/pi_tiny.py (the tiny pi0 and pi0.5) is not in this checkout")
            continue
        if not (base / "config.json").is_file():
            build_pi(folder, kind) if kind in PI else record_and_build(folder, kind, 4, 3)
        # A tiny pi loads only inside examples.pi_tiny's patch: prop runs as its module there.
        module = "examples.pi_tiny" if kind in PI else "prop_cli.cli.main"
        loading = importlib.import_module("examples.pi_tiny").tiny if kind in PI else contextlib.nullcontext
        for mode in args.mode:
            seal = mode == "sealed"
            outs, times = [], []
            for n in (1, 2):
                out = folder / f"{mode}-{n}"
                shutil.rmtree(out, ignore_errors=True)
                data, general = folder / "user", folder / "general"
                times.append(personalize(n, base, data, key, out, args.steps, seal, general, module)[0])
                with loading():
                    outs.append(trained_weights(out, key))
            rest, keys = differences(*outs)
            shown = f"{keys:11.1e}" if keys else f"{'-':>11}"
            print(f"{kind:10} {mode:9} {rest:12.1e} {shown} {times[0]:9.1f} {times[1]:10.1f}", flush=True)
    if args.keep is None:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
