"""GPU smoke test of LeRobot policies: personalize ACT, Diffusion and SmolVLA (unsealed) on CUDA at fp32
and bf16, then run each bundle on the CPU with and without the key, and check that the outputs are
finite and the key changes them. Then sealed ACT and SmolVLA (``--seal``) on CUDA at fp32 and bf16: the
bundle's base must be the original's weights bit for bit, a wrong key must run on the CPU exactly what
no key runs (the original), and the user's key must change the actions. Then real size
(``real_size``): SmolVLA (unsealed and ``--seal``) and pi0 (``--seal``, and unsealed under ``--precision
bf16 --freeze-base``: loaded, trained and reported in its checkpoint's bf16) at their published sizes, built
by benchmarks/bench_real_size.py (random weights, nothing downloaded), personalized for a few steps on
CUDA beside LeRobot's own PEFT LoRA run of the same policy: peak GPU memory
(``torch.cuda.max_memory_allocated``) and step time, within ``REAL_SIZE_BUDGET_S``. Skips cleanly
(exit 0) without CUDA or lerobot.

    .venv-lerobot/bin/python scripts/gpu_smoke_lerobot.py [WORK] [--real-size-only]

WORK holding ``general/``, ``user/`` (LeRobotDatasets with the camera) and ``act/``, ``diffusion/``,
``smolvla/`` (policy folders; the SmolVLA's VLM files in ``smolvla/vlm/``) is used as is (a GPU machine
without panda-gym); otherwise they are recorded and trained here first (examples/).
``PROP_SMOKE_DEVICE=cpu`` runs the same steps on the CPU; there ``--real-size-only --tiny`` runs the
real-size part with the tiny SmolVLA and pi0 (the code path, in a minute or two).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REAL_SIZE_BUDGET_S = 480  # the real-size part's wall-clock limit (the rest of the check fits in the 10 min)
# Each run: LeRobot's PEFT LoRA of the policy, then prop's (unsealed, sealed), 3 steps of batch 2, with
# more `prop personalize` flags; pi0 unsealed in bf16 (issue 40: its frozen base never held fp32).
REAL_SIZE_RUNS = (
    ("smolvla", "peft,sealed,prop", ""),
    ("pi0", "peft,sealed", ""),
    ("pi0", "prop", "--precision bf16 --freeze-base"),
)


def prop(*args: object) -> str:
    cmd = [sys.executable, "-m", "prop_cli.cli.main", *map(str, args)]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode:
        sys.exit(f"gpu-smoke-lerobot: prop {' '.join(map(str, args[:2]))} failed:\n{done.stderr[-2000:]}")
    return done.stdout


def prepare(work: Path) -> None:
    import shutil

    from examples import lerobot_reach_task as task
    from examples import smolvla_tiny

    task.record(work / "general", 4, 0, np.zeros(3, np.float32), camera=True)
    task.record(work / "user", 4, 50_000, task.USER_OFFSET, camera=True)
    for kind in ("act", "diffusion"):
        task.train_base(work / "general", work / kind, steps=20, kind=kind)
    vlm = smolvla_tiny.build_vlm(work / "vlm-build")
    built = smolvla_tiny.build_smolvla(vlm, task.dataset_stats(work / "general"))
    task.train_base(work / "general", work / "smolvla", steps=20, built=built)
    shutil.copytree(vlm, work / "smolvla" / "vlm")  # the folder's own VLM files: it travels alone


def main() -> None:
    import torch

    flags = {a for a in sys.argv[1:] if a.startswith("--")}
    positional = [a for a in sys.argv[1:] if not a.startswith("--")]
    device = os.environ.get("PROP_SMOKE_DEVICE", "cuda")
    if device == "cuda" and not torch.cuda.is_available():
        print("gpu-smoke-lerobot: skipped: torch sees no CUDA device")
        return
    try:
        import lerobot  # noqa: F401
    except ImportError:
        print("gpu-smoke-lerobot: skipped: lerobot is not installed (scripts/setup-lerobot.sh)")
        return
    name = torch.cuda.get_device_name() if device == "cuda" else "the CPU"
    if "--real-size-only" in flags:
        print(f"gpu-smoke-lerobot: torch {torch.__version__} on {name}")
        real_size(device, tiny="--tiny" in flags)
        print("gpu-smoke-lerobot: passed")
        return
    work = Path(positional[0]) if positional else Path(tempfile.mkdtemp(prefix="prop-gpu-lerobot-"))
    if not (work / "act").is_dir():
        prepare(work)
    print(f"gpu-smoke-lerobot: torch {torch.__version__} on {name}")
    out = Path(tempfile.mkdtemp(prefix="prop-gpu-lerobot-out-"))
    key = out / "k.bin"
    prop("keygen", key)
    for kind in ("act", "diffusion", "smolvla"):
        for precision in ("fp32", "bf16"):
            b = out / f"{kind}-{precision}.prop"
            t = time.perf_counter()
            report = json.loads(prop(
                "personalize", work / kind, "--data", work / "user", "--general-data", work / "general",
                "--key-file", key, "--out", b, "--steps", 100, "--user-rows", 16, "--null-rows", 8,
                "--neighbour-keys", 2, "--random-keys", 2, "--device", device, "--precision", precision,
                "--json",
            ))  # fmt: skip
            sec = time.perf_counter() - t
            manifest = json.loads((b / "manifest.json").read_text())
            assert manifest["config"]["precision"] == precision, manifest["config"]
            ys = {}
            for cond, extra in (("none", []), ("key", ["--key-file", key])):
                y = out / f"{kind}-{precision}-{cond}.npy"
                prop("run", b, "--input", work / "user", "--output", y, "--noise-seed", 3, *extra)
                ys[cond] = np.load(y)
            diff = float(np.abs(ys["key"] - ys["none"]).mean())
            assert np.isfinite(ys["key"]).all() and diff > 1e-4, f"{kind} {precision}: the key does nothing"
            m = report["metrics"][0]
            print(f"gpu-smoke-lerobot: {kind} {precision}: personalize 100 steps on {device} {sec:.1f} s, "
                  f"personalization {m['personalization']:.3f}, key vs no key (run on the CPU) differ by "
                  f"{diff:.4f}")  # fmt: skip
    sealed_on_device(work, out, key, device)
    real_size(device, tiny="--tiny" in flags)
    print("gpu-smoke-lerobot: passed")


def sealed_on_device(work: Path, out: Path, key: Path, device: str) -> None:
    """Sealed ACT and SmolVLA trained on ``device`` at fp32 and bf16; each bundle written from the CPU:
    its base the original's tensors, a wrong key running the original bit for bit there."""
    from safetensors.numpy import load_file

    wrong = out / "wrong.bin"
    prop("keygen", wrong)
    for kind in ("act", "smolvla"):
        original = load_file(str(work / kind / "model.safetensors"))
        for precision in ("fp32", "bf16"):
            b = out / f"{kind}-sealed-{precision}.prop"
            t = time.perf_counter()
            prop(
                "personalize", work / kind, "--data", work / "user", "--key-file", key, "--out", b, "--seal",
                "--steps", 100, "--user-rows", 16, "--device", device, "--precision", precision, "--json",
            )  # fmt: skip
            sec = time.perf_counter() - t
            base = load_file(str(b / "lerobot" / "model.safetensors"))
            same = base.keys() == original.keys() and all(np.array_equal(base[k], original[k]) for k in base)
            assert same, f"{kind} sealed {precision}: the bundle's base is not the original's weights"
            ys = {}
            for cond, extra in (("none", []), ("wrong", ["--key-file", wrong, "--allow-unenrolled-key"]),
                                ("key", ["--key-file", key])):  # fmt: skip
                y = out / f"{kind}-sealed-{precision}-{cond}.npy"
                prop("run", b, "--input", work / "user", "--output", y, "--noise-seed", 3, *extra)
                ys[cond] = np.load(y)
            what = f"{kind} sealed {precision}"
            assert np.array_equal(ys["wrong"], ys["none"]), f"{what}: a wrong key does not run the original"
            diff = float(np.abs(ys["key"] - ys["none"]).mean())
            assert np.isfinite(ys["key"]).all() and diff > 1e-4, f"{what}: the key does nothing"
            print(f"gpu-smoke-lerobot: {what}: personalize 100 steps on {device} {sec:.1f} s, base = the "
                  f"original bit for bit, a wrong key runs it exactly on the CPU, the key moves the actions "
                  f"by {diff:.4f}")  # fmt: skip



def real_size(device: str, tiny: bool = False, budget: float = REAL_SIZE_BUDGET_S) -> None:
    """SmolVLA and pi0 at their published sizes (``tiny``: examples/'s tiny ones) personalized for 3
    steps on ``device`` beside LeRobot's own PEFT LoRA run: benchmarks/bench_real_size.py's builders and
    runs, each run its own process, its table printed (peak GPU memory, step time). What would not start
    within ``budget`` seconds is named, not run."""
    import signal

    root = Path(tempfile.mkdtemp(prefix="prop-gpu-real-size-"))
    env = os.environ | {"HF_HUB_OFFLINE": "1"}
    if tiny:
        env["BENCH_REAL_SIZE_TINY"] = "1"
    t0 = time.perf_counter()
    for policy, runs, more in REAL_SIZE_RUNS:
        what = policy + (f" {runs} ({more})" if more else "")
        left = budget - (time.perf_counter() - t0)
        if left < 60:
            print(f"gpu-smoke-lerobot: real-size {what}: not run ({budget:.0f} s budget spent)")
            continue
        cmd = [
            sys.executable, "-m", "benchmarks.bench_real_size", "--policy", policy, "--runs", runs,
            "--device", device, "--steps", "3", "--batch", "2", "--episodes", "2", "--frames", "6",
            "--key-bits", "32", "--threads", str(min(8, os.cpu_count() or 1)), "--work", str(root / policy),
            "--prop-args", f"--report-budget 4 {more}".strip(), *(["--image", "32"] if tiny else []),
        ]  # fmt: skip
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                                start_new_session=True)  # fmt: skip
        try:
            stdout, stderr = proc.communicate(timeout=left)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)  # the benchmark and the run it started
            proc.communicate()
            print(f"gpu-smoke-lerobot: real-size {what}: stopped at the {budget:.0f} s budget")
            continue
        if proc.returncode:
            sys.exit(f"gpu-smoke-lerobot: real-size {what} failed:\n{(stderr or stdout)[-3000:]}")
        results = json.loads((root / policy / "results.json").read_text())
        for run, r in results.items():
            assert r.get("steps_s"), f"real-size {policy} {run}: no step ran"
            assert device != "cuda" or r.get("cuda_peak_gib", 0) > 0, f"real-size {policy} {run}: no GPU peak"
        print(f"gpu-smoke-lerobot: real-size {what} on {device} ({time.perf_counter() - t0:.0f} s so far):")
        for line in stdout.splitlines():
            if line.strip():
                print(f"gpu-smoke-lerobot:   {line}")


if __name__ == "__main__":
    main()
