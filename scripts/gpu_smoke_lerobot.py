"""GPU smoke test of LeRobot policies: personalize ACT, Diffusion and SmolVLA (unsealed) on CUDA at fp32
and bf16, then run each bundle on the CPU with and without the key, and check that the outputs are
finite and the key changes them. Then sealed ACT and SmolVLA (``--seal``) on CUDA at fp32 and bf16: the
bundle's base must be the original's weights bit for bit, a wrong key must run on the CPU exactly what
no key runs (the original), and the user's key must change the actions. Skips cleanly (exit 0) without
CUDA or lerobot.

    .venv-lerobot/bin/python scripts/gpu_smoke_lerobot.py [WORK]

WORK holding ``general/``, ``user/`` (LeRobotDatasets with the camera) and ``act/``, ``diffusion/``,
``smolvla/`` (policy folders; the SmolVLA's VLM files in ``smolvla/vlm/``) is used as is (a GPU machine
without panda-gym); otherwise they are recorded and trained here first (examples/).
``PROP_SMOKE_DEVICE=cpu`` runs the same steps on the CPU.
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

    device = os.environ.get("PROP_SMOKE_DEVICE", "cuda")
    if device == "cuda" and not torch.cuda.is_available():
        print("gpu-smoke-lerobot: skipped: torch sees no CUDA device")
        return
    try:
        import lerobot  # noqa: F401
    except ImportError:
        print("gpu-smoke-lerobot: skipped: lerobot is not installed (scripts/setup-lerobot.sh)")
        return
    work = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp(prefix="prop-gpu-lerobot-"))
    if not (work / "act").is_dir():
        prepare(work)
    name = torch.cuda.get_device_name() if device == "cuda" else "the CPU"
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


if __name__ == "__main__":
    main()
