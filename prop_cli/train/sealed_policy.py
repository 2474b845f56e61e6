"""Recipe: a policy with its own loss (a LeRobot policy), sealed: each user's payload trained on
their frames alone with the policy's own loss, the base frozen (it stays the original). No fallback
terms: a wrong key opens no record and the original runs.

It trains on ``--device`` (and ``--precision``) as the unsealed recipe does (under bf16 the frozen base
held as bf16 during the steps, ``frozen_in_bf16``, and read back from the checkpoint after them); the base
and the payloads come back to the CPU before the bundle is written, so the base it writes is the
original's tensors.
On several processes each computes its share of a step's rows, as the unsealed recipe does
(``policy``: loss parts, per-row draws, summed gradients)."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import torch

from prop_adapters import LoadedModel
from prop_cli.config import SealedConfig, TrainConfig
from prop_cli.core.batch_axes import probe_batch_axes
from prop_cli.core.device import resolve_device
from prop_cli.core.payload import Payload, PayloadSpec
from prop_cli.datasources import Dataset
from prop_cli.fit import flat_chunks

from .distributed import Ranks
from .frozen import frozen_in_bf16, held_autocast
from .loop import Optimiser, mixed_precision, run_steps
from .policy import (
    CLIP,
    REPORT_MIN_FRAMES,
    chunks,
    drawn,
    forward_rows,
    report_budget,
    row_noise,
    rows,
    spaced_frames,
    split_episodes,
    time_left,
    to_device,
    weighted,
)
from .recipe import Job, Progress, SealedUser
from .sealed import SealedRecipeBase, payload_spec, private_report


def train_payload(
    loaded: LoadedModel, spec: PayloadSpec, train: dict, tc: TrainConfig, cfg: SealedConfig, index: int,
    progress: Progress | None = None, device: torch.device | None = None, ranks: Ranks | None = None,
) -> tuple[Payload, dict[str, float]]:  # fmt: skip
    """Fit user ``index``'s payload on their frames (on ``device``, as ``loaded.module`` and ``train``)
    with the policy's own loss, the base frozen."""
    policy, module = loaded.policy, loaded.module
    dev, ranks = device or torch.device("cpu"), ranks or Ranks()
    torch.manual_seed(tc.seed + index)
    rng = np.random.default_rng((tc.seed, index))
    payload = Payload(spec, torch.Generator().manual_seed(tc.seed + index)).to(dev)
    reduce = ranks.sum_gradients if ranks.world > 1 else None
    optim = Optimiser(list(payload.parameters()), cfg.payload_lr, tc.steps, tc.lr_floor, clip=CLIP,
                      reduce=reduce)  # fmt: skip
    n = len(train["episode_index"])
    ranks.check_rows({"--user-rows": tc.user_rows})
    with payload.attached(module):
        noise = row_noise(
            policy, lambda r, _: policy.loss_parts(rows(train, torch.arange(r, device=dev) % n)),
            (tc.seed, index), module, ranks, mixed_precision(tc.precision, dev),
        )  # fmt: skip
        t = 0

        def step() -> dict[str, float]:
            nonlocal t
            picks = torch.from_numpy(rng.integers(0, n, tc.user_rows)).to(dev)
            mine = ranks.share(tc.user_rows).to(dev)  # this process's share of the step's rows
            with drawn(noise, t, mine, tc.user_rows):
                loss = weighted(policy.loss_parts(rows(train, picks[mine])), ranks)
            optim.update(loss)
            t += 1
            return {"personal": (ranks.sum_tensor(loss.detach()) if ranks.world > 1 else loss).item()}

        losses = run_steps(step, tc.steps, progress, tc.precision, dev)
    module.eval()
    return payload.eval(), losses


# Sampler runs per held-out frame of a sealed policy's report: the original's chunk and the user's key's,
# once for the private figures sealed with the payload and once through the records as anyone runs them
# (the other keys open no record and reuse the original's outputs; opening costs no sampler run).
RUNS_PER_FRAME = 4


def sealed_report_frames(frames: int, budget: int | None) -> int:
    """How many held-out frames a sealed policy's report runs within ``budget`` sampler runs (None: all);
    every key still runs on each frame kept."""
    if budget is None or frames * RUNS_PER_FRAME <= budget:
        return frames
    return min(frames, max(REPORT_MIN_FRAMES, budget // RUNS_PER_FRAME))


class SealedPolicyRecipe(SealedRecipeBase):
    def report_view(self, loaded: LoadedModel) -> torch.nn.Module:
        return loaded.policy.flat()

    def input_shape(self, loaded: LoadedModel, val: Dataset) -> dict:
        return {k: list(v) for k, v in loaded.policy.input_features.items()}

    def report_rows(self, tc: TrainConfig) -> int:
        return forward_rows(tc.user_rows)

    def train_users(
        self, job: Job[SealedConfig], datasets: list[Dataset], keys: list[np.ndarray], task: str | None,
        first_index: int = 0,
    ) -> tuple[list[SealedUser], str, dict[str, int]]:
        """Validation rows are kept as the flat view's (``prop_cli.fit.flat_chunks``); the
        keyed layers' batch axes are returned too (the audit keys the public base at those layers)."""
        loaded, tc = job.loaded, job.train
        policy, module = loaded.policy, loaded.module.eval()
        spec = payload_spec(module, replace(tc, layers=tc.layers or policy.default_layers), job.mode)
        # The policy's processors run on the CPU; the splits stay there (the flat view's rows) and a copy
        # goes to the device.
        splits = [split_episodes(policy.batches(d, "--data"), tc.val_fraction) for d in datasets]
        with policy.memo():  # what the policy computes once for every key and step (SmolVLA)
            return self._train(job, spec, splits, keys, datasets, first_index)

    def _train(
        self, job: Job, spec: PayloadSpec, splits: list, keys: list[np.ndarray], datasets: list[Dataset],
        first_index: int,
    ) -> tuple[list[SealedUser], str, dict[str, int]]:  # fmt: skip
        loaded, tc = job.loaded, job.train
        dev = resolve_device(job.device)
        policy, module = loaded.policy, loaded.module
        names = [x["name"] for x in spec.layers]
        with held_autocast(module, dev):  # a base held bf16 (keep_dtypes) computes as in the steps
            axes = probe_batch_axes(
                module, names, lambda b: policy.chunk(policy.example(b, splits[0][0])),
                f"the policy {loaded.source}",
            )  # fmt: skip
        module.requires_grad_(False)
        out = []
        budget = report_budget(tc, module)
        try:
            module.to(dev)
            per = self.report_rows(tc)
            for i, ((tr, val), bits) in enumerate(zip(splits, keys), first_index):
                # Under --precision bf16 the frozen base is held bf16 while the payload trains, then read
                # back exactly from the checkpoint: the report and the bundle see the original's weights.
                job.say(f"user {i + 1}: setting up the payload's frames and noise, then {tc.steps} steps")
                restore = frozen_in_bf16(module, loaded) if tc.precision == "bf16" else None
                try:
                    payload, losses = train_payload(
                        loaded, spec, to_device(tr, dev), tc, job.mode, i, job.progress, dev, job.ranks
                    )  # fmt: skip
                finally:
                    if restore is not None:
                        restore()
                # The report within --report-budget (by the policy's size by default), as the unsealed one.
                n = len(val["episode_index"])
                val = spaced_frames(val, sealed_report_frames(n, budget))
                f = len(val["episode_index"])
                job.say(f"report of user {i + 1}: {f * RUNS_PER_FRAME} sampler runs ({f} of {n} held-out "
                        f"frames; --report-budget {budget or 'none'})")  # fmt: skip
                on_dev = to_device(val, dev)
                folded = policy.on(payload.fold(module))
                started, runs = time.perf_counter(), f * RUNS_PER_FRAME
                with held_autocast(module, dev):
                    b = chunks(policy, on_dev, per)
                job.say(f"report of user {i + 1}: {f} of {runs} sampler runs done (the original's chunks); "
                        f"{time_left(started, f, runs)}")  # fmt: skip
                with held_autocast(module, dev):
                    o = chunks(folded, on_dev, per)
                left = time_left(started, 2 * f, runs)
                job.say(f"report of user {i + 1}: {2 * f} of {runs} sampler runs done (your payload's "
                        f"chunks; then every key through the records); {left}")  # fmt: skip
                private = private_report(o.cpu(), val["action"], b.cpu(), "regression", losses, job)
                if len(val["episode_index"]) < n:
                    private["coverage"] = {"ran": {"frames": len(val["episode_index"])}, "of": {"frames": n},
                                           "budget": budget}  # fmt: skip
                flat_val = flat_chunks(policy, val, datasets[i - first_index].path)
                out.append(SealedUser(payload.to("cpu"), private, bits, flat_val))
        finally:
            module.to("cpu")  # the bundle's base is written, and runs, from the CPU
        return out, "regression", axes


RECIPE = SealedPolicyRecipe()
