"""A PRoP training step vs LeRobot's own training step on the same small policy and the same row count.

    bash scripts/setup-lerobot.sh
    OMP_NUM_THREADS=1 .venv-lerobot/bin/python -m benchmarks.bench_lerobot_step --policy diffusion --reps 30
    .venv-lerobot/bin/python -m benchmarks.bench_lerobot_step --policy pi0 --reps 30  # default threads

LeRobot step: policy.forward(32 rows) -> backward -> clip 10 -> AdamW (lerobot_train.update_policy).
PRoP step: prop_cli.train.policy.PolicyTrainer.step, the step `prop personalize` runs: 16 user rows
through the policy's loss under the user key, 8 null + 8 sampled-key rows through the deployed path
against the original (ACT: its cached chunks; Diffusion / SmolVLA / pi0 / pi0.5: its denoiser /
velocity on noised rows drawn once, both terms in one forward), key encoder in the graph, same clip. The
two alternate (the machine is shared); medians and their ratio are printed. Target (issues 11, 22 and
29): <= 1.3x. pi0 and pi0.5 are the tiny ones of examples/pi_tiny.py (2+2-layer Gemmas of width 64),
built and loaded under its size patch.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from examples.pi_tiny import tiny
from examples.smolvla_tiny import KINDS, record_and_build
from prop_adapters import load_checkpoint
from prop_cli.config import PersonalizeConfig
from prop_cli.datasources import load_data
from prop_cli.train import User
from prop_cli.train.policy import PolicyTrainer


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reps", type=int, default=30)
    ap.add_argument("--policy", choices=KINDS, default="act")
    ap.add_argument("--full-size", action="store_true",
                    help="Diffusion at LeRobot's default U-Net (down_dims 512/1024/2048, 250M parameters)")
    args = ap.parse_args(argv)
    with tiny():  # a tiny pi0 / pi0.5 loads only under it; the other policies do not see it
        bench(args)


def bench(args: argparse.Namespace) -> None:
    torch.manual_seed(0)
    work = Path(tempfile.mkdtemp(prefix="prop-bench-lerobot-"))
    full = {"down_dims": (512, 1024, 2048), "diffusion_step_embed_dim": 128} if args.full_size else {}
    base = record_and_build(work, args.policy, 8, 4, **full)
    cfg = PersonalizeConfig.of(steps=10**6, user_rows=16, null_rows=8, neighbour_keys=4, random_keys=4,
                            samples_per_key=1, null_weight=2.0, base_lr_scale=0.1)  # fmt: skip
    key = np.random.default_rng(0).integers(0, 2, 128).astype(np.uint8)
    trainer = PolicyTrainer(
        load_checkpoint(base), [User(load_data(work / "user"), key)], cfg.train, cfg.mode,
        load_data(work / "general"),
    )
    m = cfg.mode
    rows = cfg.train.user_rows + m.null_rows + (m.neighbour_keys + m.random_keys) * m.samples_per_key

    lerobot = load_checkpoint(base)  # a second copy of the same policy, without keys
    data = lerobot.policy.batches(load_data(work / "general"), "--data")
    data.pop("episode_index")
    opt = torch.optim.AdamW(lerobot.module.parameters(), lr=1e-5, weight_decay=1e-4)
    rng = np.random.default_rng(0)

    def lerobot_step() -> None:
        idx = torch.from_numpy(rng.integers(0, len(data["action"]), rows))
        lerobot.module.train()
        loss, _ = lerobot.module.forward({k: v[idx] for k, v in data.items()})
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(lerobot.module.parameters(), 10.0)
        opt.step()

    torch.set_flush_denormal(True)
    for _ in range(5):  # warm-up
        lerobot_step()
        trainer.step()
    times: dict[str, list[float]] = {"lerobot": [], "prop": []}
    for _ in range(args.reps):
        for name, fn in (("lerobot", lerobot_step), ("prop", trainer.step)):
            t = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t)
    med = {k: statistics.median(v) * 1000 for k, v in times.items()}
    unet = "512/1024/2048" if args.full_size else "32/64/128"
    what = {"act": "ACT (dim 64, chunk 10)", "diffusion": f"Diffusion (U-Net {unet}, horizon 16)",
            "smolvla": "SmolVLA (tiny SmolVLM, 2 layers; chunk 10)",
            "pi0": "pi0 (tiny: 2+2-layer Gemmas of width 64, 2-layer SigLIP; chunk 10)",
            "pi05": "pi0.5 (tiny: 2+2-layer Gemmas of width 64, 2-layer SigLIP; chunk 10)"}  # fmt: skip
    print(f"{what[args.policy]}, {rows} rows per step, {args.reps} alternating reps, "
          f"{torch.get_num_threads()} torch threads, medians:")  # fmt: skip
    print(f"  LeRobot step {med['lerobot']:.1f} ms, PRoP step {med['prop']:.1f} ms, "
          f"ratio {med['prop'] / med['lerobot']:.2f}x (target <= 1.3x)")  # fmt: skip


if __name__ == "__main__":
    main()
