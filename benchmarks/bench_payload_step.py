"""A sealed payload's training step vs a plain peft LoRA step on the same policy, rows, rank and optimiser.

    bash scripts/setup-lerobot.sh
    OMP_NUM_THREADS=1 .venv-lerobot/bin/python -m benchmarks.bench_payload_step --policy diffusion --reps 30
    .venv-lerobot/bin/python -m benchmarks.bench_payload_step --policy pi0 --reps 30  # default threads

Payload step: what `prop personalize --seal` runs per step (``prop_cli.train.sealed_policy``): the
payload applied to the frozen base through weight parametrizations, the policy's own loss on 32 user
rows, backward, clip 10, prop's Adam. Plain step: the same policy wrapped by peft's ``get_peft_model``
(LoRA of the same rank on the same layers), the same loss, rows, clip and optimiser. Both payload kinds
are timed: ``peft-lora`` (W + B A, what peft computes) and ``lora`` (W + B A, then a per-input delta).
The steps alternate (the machine is shared); medians and ratios are printed. Target (issues 22 and 29):
<= 1.1x. pi0 and pi0.5 are the tiny ones of examples/pi_tiny.py, built and loaded under its size patch.
"""

from __future__ import annotations

import argparse
import copy
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
from prop_cli.core.payload import Payload
from prop_cli.datasources import load_data
from prop_cli.train.loop import Optimiser
from prop_cli.train.policy import CLIP, rows
from prop_cli.train.sealed import payload_spec


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--policy", choices=KINDS, default="diffusion")
    ap.add_argument("--reps", type=int, default=30)
    ap.add_argument("--rank", type=int, default=4)
    args = ap.parse_args(argv)
    with tiny():  # a tiny pi0 / pi0.5 loads only under it; the other policies do not see it
        bench(args)


def bench(args: argparse.Namespace) -> None:
    from peft import LoraConfig, get_peft_model

    torch.manual_seed(0)
    work = Path(tempfile.mkdtemp(prefix="prop-bench-payload-"))
    record_and_build(work, args.policy, 2, 6)
    rng = np.random.default_rng(0)
    steps: dict = {}
    attached = []  # the payloads stay attached while the benchmark runs (a dropped context detaches)
    for kind in ("peft-lora", "lora"):
        loaded = load_checkpoint(work / args.policy)
        policy, module = loaded.policy, loaded.module.eval().requires_grad_(False)
        cfg = PersonalizeConfig.of(
            seal=True, payload=kind, payload_rank=args.rank, layers=policy.default_layers
        )
        spec = payload_spec(module, cfg.train, cfg.mode)
        data = policy.batches(load_data(work / "user"), "--data")
        payload = Payload(spec, torch.Generator().manual_seed(0))
        optim = Optimiser(list(payload.parameters()), 1e-3, 10**6, 1.0, clip=CLIP)
        attached.append(payload.attached(module))
        attached[-1].__enter__()

        def step(policy=policy, data=data, optim=optim) -> None:
            optim.update(policy.loss(rows(data, torch.from_numpy(rng.integers(0, len(data["action"]), 32)))))

        steps[f"payload {kind}"] = step
    names = [layer["name"] for layer in spec.layers]
    plain = load_checkpoint(work / args.policy)
    wrapped = get_peft_model(copy.deepcopy(plain.module), LoraConfig(r=args.rank, lora_alpha=args.rank,
                                                                      target_modules=names))  # fmt: skip
    plain_policy = plain.policy.on(wrapped.base_model.model)
    data = plain.policy.batches(load_data(work / "user"), "--data")
    trainable = [p for p in wrapped.parameters() if p.requires_grad]
    plain_optim = Optimiser(trainable, 1e-3, 10**6, 1.0, clip=CLIP)

    def plain_step() -> None:
        idx = torch.from_numpy(rng.integers(0, len(data["action"]), 32))
        plain_optim.update(plain_policy.loss(rows(data, idx)))

    steps = {"peft LoRA": plain_step, **steps}
    torch.set_flush_denormal(True)
    for fn in steps.values():  # warm-up
        for _ in range(3):
            fn()
    times: dict[str, list[float]] = {k: [] for k in steps}
    for _ in range(args.reps):
        for name, fn in steps.items():
            t = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t)
    med = {k: statistics.median(v) * 1000 for k, v in times.items()}
    print(f"{args.policy}: {len(names)} layers, rank {args.rank}, 32 rows, {args.reps} alternating reps, "
          f"{torch.get_num_threads()} torch threads, medians:")  # fmt: skip
    for name, ms in med.items():
        print(f"  {name:18s} {ms:7.1f} ms  {ms / med['peft LoRA']:.2f}x the peft LoRA step (target <= 1.1x)")


if __name__ == "__main__":
    main()
