"""A real-size SmolVLA's training step once its frames were seen: prop's unsealed step beside LeRobot's
own, alternated in one process (the same machine load for both), on what ``bench_real_size`` built.

    .venv-lerobot/bin/python -m benchmarks.bench_real_size --work DIR --runs lerobot   # builds DIR
    .venv-lerobot/bin/python -m benchmarks.bench_warm_step --work DIR [--steps 4]

``bench_real_size`` times a short run's first steps, where most rows are frames prop meets for the first
time (its memo, ``SmolVLAProtocol.memo``, computes their image embedding and the VLM's keys and values
for their image + language tokens then) and the original's fallback targets are computed as they are
first drawn. Here prop's step draws the same rows every step (its row generator reseeded), so after the
first (cold: targets and memo filled) every step is a step over frames seen before, as in a run longer
than an epoch whose frames fit the memo. LeRobot's step (its forward on its preprocessed batch of
``--batch`` frames, backward, grad clip, AdamW) has no memo: every step costs the same. Both on
``--threads`` threads. With ``--fallback-every K`` also prop's step as that flag runs it: K consecutive
steps (one with the fallback rows, K - 1 with the user's rows and the pull alone) timed together, over K.
Then the report's sampler (6 rows of 2 held-out frames) with and without the
prefix memo, ``--chunks`` times each. Printed: each run's wall and CPU seconds, the medians and their ratios.
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import replace
from pathlib import Path


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, required=True, help="bench_real_size's --work (built there)")
    ap.add_argument("--steps", type=int, default=4, help="timed steps of each, after one cold step")
    ap.add_argument("--batch", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--null-rows", type=int, default=None, help="prop's no-key rows (default: --batch)")
    ap.add_argument("--chunks", type=int, default=2, help="sampler runs timed with and without the memo")
    ap.add_argument("--fallback-every", type=int, default=3,
                    help="also time prop's step with --fallback-every K (the mean over K steps; 1: skip)")
    args = ap.parse_args(argv)
    import numpy as np
    import torch

    torch.set_num_threads(args.threads)
    from lerobot.datasets.factory import resolve_delta_timestamps
    from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy

    from prop_adapters import load_checkpoint
    from prop_adapters.lerobot import smolvla
    from prop_cli.config import PersonalizeConfig
    from prop_cli.datasources import load_data
    from prop_cli.train import User
    from prop_cli.train.policy import PolicyTrainer, rows

    folder, data = args.work / "smolvla", args.work / "data"
    # LeRobot's own: from_pretrained, its preprocessor, one batch of its dataset, its AdamW preset.
    torch.manual_seed(0)
    theirs = SmolVLAPolicy.from_pretrained(str(folder))
    pre, _ = make_pre_post_processors(theirs.config, pretrained_path=str(folder))
    meta = LeRobotDatasetMetadata("local/real-size", root=data)
    stamps = resolve_delta_timestamps(theirs.config, meta)
    ds = LeRobotDataset("local/real-size", root=data, delta_timestamps=stamps)
    batch = pre(next(iter(torch.utils.data.DataLoader(ds, batch_size=args.batch, shuffle=False))))
    preset = theirs.config.get_optimizer_preset()
    params = [p for p in theirs.parameters() if p.requires_grad]
    optimizer = preset.build(theirs.get_optim_params())
    theirs.train()

    def lerobot_step() -> None:
        loss, _ = theirs.forward(batch)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, preset.grad_clip_norm)
        optimizer.step()
        optimizer.zero_grad()

    # prop's: the PolicyTrainer personalize runs (its step: --batch user rows, --batch null rows, one
    # neighbour, one random key and one far code row), within the policy's memo as personalize runs it.
    loaded = load_checkpoint(folder)
    key = np.random.default_rng(0).integers(0, 2, 128).astype(np.uint8)
    null = args.null_rows or args.batch
    cfg = PersonalizeConfig.of(steps=args.steps + 1, user_rows=args.batch, null_rows=null, neighbour_keys=1,
                               random_keys=1, far_codes=1, samples_per_key=1)  # fmt: skip
    with loaded.policy.memo():
        t = PolicyTrainer(loaded, [User(load_data(data), key)], cfg.train, cfg.mode, None)
        state = t.rng.bit_generator.state

        def prop_step() -> None:
            t.rng.bit_generator.state = state  # the same rows every step
            t.step()

        cold = time.perf_counter()
        prop_step()
        cold = time.perf_counter() - cold
        every = args.fallback_every
        amortised = f"prop --fallback-every {every}"

        def amortised_step() -> None:  # K steps from a step that runs the fallback rows, timed together
            t.cfg = replace(base_cfg, fallback_every=every)
            t.t = 0
            for _ in range(every):
                prop_step()
            t.cfg = base_cfg

        base_cfg = t.cfg
        runs = [("lerobot", lerobot_step, 1), ("prop", prop_step, 1)]
        if every > 1:
            runs.append((amortised, amortised_step, every))
        times: dict[str, list[float]] = {name: [] for name, _, _ in runs}
        cpu: dict[str, list[float]] = {name: [] for name, _, _ in runs}
        for _ in range(args.steps):
            for name, step, per in runs:
                s, c = time.perf_counter(), time.process_time()
                step()
                times[name].append((time.perf_counter() - s) / per)
                cpu[name].append((time.process_time() - c) / per)
        # The report's sampler (the deployed chunk) on 6 rows of 2 held-out frames, as its key sweep runs
        # them, with and without the prefix memo (the image memo on in both), alternated.
        val = rows(t.splits[0][1], torch.tensor([0, 1] * 3))
        own = smolvla.PrefixMemo.block

        def off(memo, *a) -> None:
            memo.last = None

        with torch.no_grad():
            t.policy.chunk(val)  # the frames' image embeddings and blocks, once
            for _ in range(args.chunks):
                for name, block in (("sampler, no prefix memo", off), ("sampler, prefix memo", own)):
                    smolvla.PrefixMemo.block = block
                    s = time.perf_counter()
                    t.policy.chunk(val)
                    times.setdefault(name, []).append(time.perf_counter() - s)
            smolvla.PrefixMemo.block = own
    med = {k: statistics.median(v) for k, v in times.items()}
    print(f"prop's first (cold) step: {cold:.1f} s (the original's targets and its frames' memo filled)")
    for k, v in times.items():
        print(f"{k}: steps {', '.join(f'{x:.2f}' for x in v)} s; median {med[k]:.2f} s")
    # CPU seconds as well: on a shared machine a step's wall time is mostly its wait for a core (with
    # --threads 1 its CPU time is its compute).
    cpu_med = {k: statistics.median(v) for k, v in cpu.items()}
    for k, v in cpu.items():
        print(f"{k}: CPU {', '.join(f'{x:.2f}' for x in v)} s; median {cpu_med[k]:.2f} s")
    names = ["prop"] + ([f"prop --fallback-every {args.fallback_every}"] if args.fallback_every > 1 else [])
    for name in names:
        print(f"{name} / lerobot, warm step: {med[name] / med['lerobot']:.2f}x wall, "
              f"{cpu_med[name] / cpu_med['lerobot']:.2f}x CPU")
    if args.chunks:
        a, b = med["sampler, prefix memo"], med["sampler, no prefix memo"]
        print(f"sampler on 6 rows, prefix memo / none: {a / b:.2f}x")


if __name__ == "__main__":
    main()
