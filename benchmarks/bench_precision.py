"""What --precision bf16 buys: the step loop's time, fp32 against bf16, on one device.

    python -m benchmarks.bench_precision [--device cuda] [--steps 500] [--sizes 16,256,256,4 ...]

Per MLP (``--sizes``, one per layer chain) and mode (unsealed, sealed): a personalize through the
library at each precision, timed from the end of its first step to the end of its last (loading,
the fallback pool and the final report are left out, and so is the first step's warm-up). A first,
untimed personalize warms the device. Prints one line per run and the bf16/fp32 time ratio.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from prop_cli.api import KeySource, personalize_checkpoint
from prop_cli.config import PersonalizeConfig
from tests.conftest import make_mlp_checkpoint


def _timed(d: Path, cfg: PersonalizeConfig, bits: np.ndarray, device: str, tag: str) -> float:
    marks: dict[int, float] = {}

    def progress(step: int, _: dict[str, float]) -> None:
        if step in (1, cfg.train.steps):
            if device.startswith("cuda"):
                torch.cuda.synchronize()
            marks[step] = time.perf_counter()

    personalize_checkpoint(
        str(d / "model.safetensors"), [(d / "mine.npz", KeySource(bits, "file"))], d / f"{tag}.prop", cfg,
        device=device, progress=progress, force=True,
    )  # fmt: skip
    return marks[cfg.train.steps] - marks[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument("--sizes", nargs="+", default=["16,256,256,4"])
    args = ap.parse_args()
    where = torch.cuda.get_device_name() if args.device.startswith("cuda") else "CPU"
    print(f"torch {torch.__version__} on {where}, {args.steps} steps")
    bits = np.random.default_rng(0).integers(0, 2, 128).astype(np.uint8)
    for spec in args.sizes:
        sizes = tuple(int(s) for s in spec.split(","))
        with tempfile.TemporaryDirectory() as tmp:
            d = Path(tmp)
            make_mlp_checkpoint(d / "model.safetensors", sizes=sizes)
            rng = np.random.default_rng(0)
            x = rng.uniform(-1, 1, (2000, sizes[0])).astype(np.float32)
            y = np.tanh(x[:, : sizes[-1]] * 2).astype(np.float32)
            np.savez(d / "mine.npz", x=x, y=y)
            _timed(d, PersonalizeConfig.of(steps=20), bits, args.device, "warm")
            for seal in (False, True):
                took = {}
                for precision in ("fp32", "bf16"):
                    cfg = PersonalizeConfig.of(steps=args.steps, seal=seal, precision=precision)
                    took[precision] = _timed(d, cfg, bits, args.device, precision)
                mode = "sealed" if seal else "unsealed"
                ms = {p: 1e3 * t / (args.steps - 1) for p, t in took.items()}
                print(
                    f"MLP {spec} {mode}: fp32 {ms['fp32']:.2f} ms/step, bf16 {ms['bf16']:.2f} ms/step, "
                    f"bf16/fp32 {took['bf16'] / took['fp32']:.2f}x"
                )


if __name__ == "__main__":
    main()
