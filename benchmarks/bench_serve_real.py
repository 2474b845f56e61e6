"""Keying's own cost at real size (issue 39): the added latency of serving keyed rows against the base
policy's own forward on the same batch, for LeRobot ACT and SmolVLA at their published sizes (random
weights, nothing downloaded). Goal: at most 5% of the base's time.

    bash scripts/setup-lerobot.sh
    OMP_NUM_THREADS=1 .venv-lerobot/bin/python -m benchmarks.bench_serve_real [--policy act smolvla]
        [--batch 1 8] [--repeat 9] [--rank 8]

What is built (``--work``, kept between runs):
- **ACT**: LeRobot's ``ACTConfig`` defaults (ResNet-18 backbone, random weights: no ImageNet download;
  512-wide transformer, 4 encoder and 1 decoder layers, chunk 100), one camera of ``--image`` pixels
  square (480: ALOHA's height), a 6-value state and action: 51.6 M parameters;
- **SmolVLA**: ``benchmarks/bench_real_size.py``'s (SmolVLM2-500M's published configs, LeRobot's
  ``SmolVLAConfig`` defaults, images resized to 512x512, 10 flow steps): 450 M parameters.

Each policy is loaded as prop loads a checkpoint, and its served rows run as ``prop serve`` runs them
(``prop_cli/serve/chunks.py``'s ``ChunkRunner``: each request's frame preprocessed, one
``predict_action_chunk`` of the batch, postprocessed): **base**, every row without a key, in one forward
(``--batch-no-key``'s path: the base policy's own forward on the batch); **(a)**, every row one user's
sealed LoRA payload (rank ``--rank`` on the policy's default keyed layers, what ``prop personalize --seal
--payload lora`` writes); **(b)**, each row another user's payload. The three run interleaved,
``--repeat`` rounds after a warm-up, each round on fresh frames (the same frames for the three, each of
them first in turn). Printed: each one's fastest call (wall clock, ms), and the keyed rows' added time as
a share of the base's, measured in the same run, two ways: fastest against fastest (the least disturbed
call of each, as timeit takes the best), and the median over the rounds of keyed / base (same frames,
same round), each by the wall clock and by this process's CPU time (steadier where other jobs load the
machine: run it with OMP_NUM_THREADS=1).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

from benchmarks.bench_real_size import TASK_TEXT, build, build_data, features

GOAL = 0.05  # the added latency of keying, as a share of the base's own


def build_act(work: Path, image: int, stats: dict, seed: int = 0) -> Path:
    """ACT at LeRobot's defaults (random weights) as a policy folder under ``work``."""
    out = work / "act"
    if (out / "model.safetensors").is_file():
        return out
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.policies.act.modeling_act import ACTPolicy
    from lerobot.policies.factory import make_pre_post_processors

    cfg = ACTConfig(**features(image), device="cpu", pretrained_backbone_weights=None)
    torch.manual_seed(seed)
    policy = ACTPolicy(cfg)
    pre, post = make_pre_post_processors(cfg, dataset_stats=stats)
    for part in (policy, pre, post):
        part.save_pretrained(out)
    return out


def payloads(module: torch.nn.Module, names: list[str], rank: int, n: int) -> list:
    """``n`` users' sealed LoRA payloads (rank ``rank``) on ``names``, away from the base."""
    from prop_cli.core.layers import describe_layer
    from prop_cli.core.payload import Payload, PayloadSpec

    mods = dict(module.named_modules())
    spec = PayloadSpec("lora", [describe_layer(x, mods[x]) for x in names], rank=rank)
    out = []
    for seed in range(n):
        p = Payload(spec, torch.Generator().manual_seed(seed))
        g = torch.Generator().manual_seed(seed + 1000)
        with torch.no_grad():
            for t in p.params.values():
                t.add_(torch.randn(t.shape, generator=g) * 0.01)
        out.append(p)
    return out


def runner_of(path: Path):
    """``prop serve``'s ChunkRunner over the policy at ``path``, loaded as prop loads a checkpoint, with a
    sealed bundle's payload table on the policy's default keyed layers; and those layers."""
    from prop_adapters import load_checkpoint
    from prop_cli.core.layers import select_layers
    from prop_cli.serve.chunks import ChunkRunner

    loaded = load_checkpoint(str(path))
    names = select_layers(loaded.module, loaded.policy.default_layers)
    # What ChunkRunner reads of a sealed bundle: its loaded policy, its keyed layers, its path.
    bundle = SimpleNamespace(loaded=loaded, mode=SimpleNamespace(keyed=None, layer_names=names), path=path)
    runner = ChunkRunner(bundle, None, batch_no_key=True)  # type: ignore[arg-type]
    return runner, names


def frames(runner, n: int, rng: np.random.Generator) -> list[dict]:
    shapes = runner.controller().features
    out = []
    for _ in range(n):
        f = {k: rng.uniform(0, 1, tuple(s)).astype(np.float32) for k, s in shapes.items()}
        if runner.protocol.takes_instruction:
            f["task"] = TASK_TEXT
        out.append(f)
    return out


def measure(name: str, path: Path, batches: list[int], repeat: int, rank: int) -> list[str]:
    from prop_cli.core.payload import Payload
    from prop_cli.serve.rows import PayloadTable, gathered

    runner, names = runner_of(path)
    module = runner.module
    params = sum(p.numel() for p in module.parameters()) / 1e6
    users = payloads(module, names, rank, max(batches))
    spec = users[0].spec
    runner.table = PayloadTable(spec)
    assert all(gathered(module, p) for p in users), "a keyed layer is not a plain linear: rows would fold"
    controller = runner.controller()
    rng = np.random.default_rng(0)
    lines = [f"{name}: {params:.1f} M parameters, {len(names)} keyed layers, LoRA rank {rank} "
             f"({sum(p.numel() for p in users[0].params.values()) / 1e6:.2f} M values per user)"]  # fmt: skip
    print(lines[0], flush=True)
    for b in batches:
        who = {"base": [None] * b, "(a) one user": [users[0]] * b, "(b) users": users[:b]}

        def call(behaviours: list[Payload | None], obs: list[dict]) -> tuple[float, float]:
            requests = [runner.request(controller, p, f) for p, f in zip(behaviours, obs)]
            t, c = time.perf_counter(), time.process_time()
            runner.run(requests)
            return time.perf_counter() - t, time.process_time() - c

        warm = frames(runner, b, rng)
        for behaviours in who.values():  # warm-up: the table's slots, allocator, kernels
            call(behaviours, warm)
        times: dict[str, list[tuple[float, float]]] = {k: [] for k in who}
        order = list(who)
        for i in range(repeat):
            obs = frames(runner, b, rng)
            for k in order[i % 3 :] + order[: i % 3]:  # interleaved, each first in turn: load hits all alike
                times[k].append(call(who[k], obs))
        cells = []
        for k in ("(a) one user", "(b) users"):
            row = []
            for j, clock in enumerate(("wall", "CPU")):
                base = [x[j] for x in times["base"]]
                keyed = [x[j] for x in times[k]]
                best = min(keyed) / min(base) - 1  # the least disturbed call of each
                paired = float(np.median([y / x for x, y in zip(base, keyed)])) - 1  # same frames, same round
                row.append(f"{clock} {100 * best:+.1f}% / {100 * paired:+.1f}%")
            cells.append(f"{k} {1e3 * min(x[0] for x in times[k]):.0f} ms: " + ", ".join(row))
        base_ms = 1e3 * min(x[0] for x in times["base"])
        lines.append(f"  batch {b:>2}: base {base_ms:.0f} ms; " + "; ".join(cells))
        print(lines[-1], flush=True)
    return lines


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--policy", nargs="+", choices=("act", "smolvla"), default=["act", "smolvla"])
    ap.add_argument("--batch", nargs="+", type=int, default=[1, 8])
    ap.add_argument("--repeat", type=int, default=9, help="timed rounds (after one warm-up)")
    ap.add_argument("--rank", type=int, default=8, help="the users' LoRA rank")
    ap.add_argument("--image", type=int, default=480, help="camera frames' side (SmolVLA resizes to 512)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/prop-bench-serve-real"))
    args = ap.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    print(f"$ OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', '')} python -m benchmarks.bench_serve_real "
          f"--policy {' '.join(args.policy)} --batch {' '.join(map(str, args.batch))} --repeat {args.repeat} "
          f"--rank {args.rank}")  # fmt: skip
    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} threads, CPU, load "
        f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs; {args.repeat} rounds; "
        "added time: fastest / median of the rounds",
        flush=True,
    )
    stats = build_data(args.work / "data", args.image, episodes=1, frames=4)
    paths = {}
    if "act" in args.policy:
        paths["act"] = build_act(args.work, args.image, stats)
    if "smolvla" in args.policy:
        paths["smolvla"] = build(args.work, args.image, episodes=1, frames=4)[0]
    for name, path in paths.items():
        with torch.inference_mode():
            measure(name, path, args.batch, args.repeat, args.rank)


if __name__ == "__main__":
    main()
