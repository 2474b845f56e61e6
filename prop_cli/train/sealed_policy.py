"""Recipe: a policy with its own loss (LeRobot ACT, Diffusion), sealed: each user's payload trained on
their frames alone with the policy's own loss, the base frozen (it stays the original). No fallback
terms: a wrong key opens no record and the original runs."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from prop_adapters import LoadedModel
from prop_adapters.lerobot.flat import flat_module
from prop_cli.config import PersonalizeConfig
from prop_cli.core.batch_axes import probe_batch_axes
from prop_cli.core.payload import Payload, PayloadSpec
from prop_cli.datasources import Dataset
from prop_cli.fit import flat_chunks

from .loop import Optimiser, run_steps
from .policy import CLIP, check_cpu, chunks, forward_rows, rows, split_episodes
from .recipe import Job, Progress, SealedUser
from .sealed import SealedRecipeBase, payload_spec, private_report


def train_payload(
    loaded: LoadedModel, spec: PayloadSpec, train: dict, cfg: PersonalizeConfig, index: int,
    progress: Progress | None = None,
) -> tuple[Payload, dict[str, float]]:
    """Fit user ``index``'s payload on their frames with the policy's own loss, the base frozen."""
    policy, module = loaded.policy, loaded.module
    torch.manual_seed(cfg.seed + index)
    rng = np.random.default_rng((cfg.seed, index))
    payload = Payload(spec, torch.Generator().manual_seed(cfg.seed + index))
    optim = Optimiser(list(payload.parameters()), cfg.payload_lr, cfg.steps, cfg.lr_floor, clip=CLIP)
    n = len(train["episode_index"])
    with payload.attached(module):

        def step() -> dict[str, float]:
            loss = policy.loss(rows(train, torch.from_numpy(rng.integers(0, n, cfg.user_rows))))
            optim.update(loss)
            return {"personal": loss.item()}

        losses = run_steps(step, cfg.steps, progress, cfg.precision, "cpu")  # policies: CPU only
    module.eval()
    return payload.eval(), losses


class SealedPolicyRecipe(SealedRecipeBase):
    def report_view(self, loaded: LoadedModel) -> torch.nn.Module:
        return flat_module(loaded.policy)

    def input_shape(self, loaded: LoadedModel, val: Dataset) -> dict:
        return {k: list(v) for k, v in loaded.policy.input_features.items()}

    def report_rows(self, cfg: PersonalizeConfig) -> int:
        return forward_rows(cfg, cfg.user_rows)

    def train_users(
        self, job: Job, datasets: list[Dataset], keys: list[np.ndarray], task: str | None,
        first_index: int = 0,
    ) -> tuple[list[SealedUser], str, dict[str, int]]:
        """Validation rows are kept as the flat view's (``prop_cli.fit.flat_chunks``); the
        keyed layers' batch axes are returned too (the audit keys the public base at those layers)."""
        loaded, cfg = job.loaded, job.cfg
        check_cpu(job.device)
        policy, module = loaded.policy, loaded.module.eval()
        spec = payload_spec(module, replace(cfg, layers=cfg.layers or policy.default_layers))
        splits = [split_episodes(policy.batches(d, "--data"), cfg.val_fraction) for d in datasets]
        with policy.memo():  # what the policy computes once for every key and step (SmolVLA)
            return self._train(job, spec, splits, keys, datasets, first_index)

    def _train(
        self, job: Job, spec: PayloadSpec, splits: list, keys: list[np.ndarray], datasets: list[Dataset],
        first_index: int,
    ) -> tuple[list[SealedUser], str, dict[str, int]]:  # fmt: skip
        loaded, cfg = job.loaded, job.cfg
        policy, module = loaded.policy, loaded.module
        names = [x["name"] for x in spec.layers]
        axes = probe_batch_axes(
            module, names, lambda b: policy.chunk(policy.example(b, splits[0][0])),
            f"the policy {loaded.source}",
        )  # fmt: skip
        module.requires_grad_(False)
        out = []
        for i, ((tr, val), bits) in enumerate(zip(splits, keys), first_index):
            payload, losses = train_payload(loaded, spec, tr, cfg, i, job.progress)
            folded = policy.on(payload.fold(module))
            per = self.report_rows(cfg)
            b, o, p = chunks(policy, val, per), chunks(folded, val, per), val["action"]
            private = private_report(o, p, b, "regression", losses, cfg)
            flat_val = flat_chunks(policy, val, datasets[i - first_index].path)
            out.append(SealedUser(payload, private, bits, flat_val))
        return out, "regression", axes


RECIPE = SealedPolicyRecipe()
