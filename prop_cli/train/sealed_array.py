"""Recipe: an array model, sealed: each user's payload fitted on their data alone, the base frozen (it
stays the original). No fallback terms: a wrong key opens no record and the original runs. On several
processes (``distributed``) each computes its share of a step's rows and the gradients are summed."""

from __future__ import annotations

import numpy as np
import torch

from prop_adapters import LoadedModel
from prop_cli.config import SealedConfig, TrainConfig
from prop_cli.core.device import resolve_device
from prop_cli.core.payload import Payload, PayloadSpec
from prop_cli.datasources import Dataset
from prop_cli.fit import split

from .data import prepare_users, targets_tensor
from .distributed import Ranks
from .frozen import frozen_in_bf16
from .loop import Optimiser, run_steps
from .objective import row_loss
from .recipe import Job, Progress, SealedUser
from .sealed import SealedRecipeBase, payload_spec, private_report


def train_payload(
    module: torch.nn.Module,
    spec: PayloadSpec,
    train: Dataset,
    task: str,
    tc: TrainConfig,
    cfg: SealedConfig,
    dev: torch.device,
    progress: Progress | None = None,
    ranks: Ranks | None = None,
) -> tuple[Payload, dict[str, float]]:
    """Fit one user's payload on their data, the base frozen."""
    ranks = ranks or Ranks()
    gen = torch.Generator().manual_seed(tc.seed)
    payload = Payload(spec, gen).to(dev)
    x = torch.from_numpy(train.x).to(dev)
    y = targets_tensor(train, task).to(dev)
    rng = np.random.default_rng(tc.seed)
    reduce = ranks.sum_gradients if ranks.world > 1 else None
    optim = Optimiser(list(payload.parameters()), cfg.payload_lr, tc.steps, tc.lr_floor, reduce=reduce)
    module.requires_grad_(False)
    ranks.check_rows({"--user-rows": tc.user_rows})
    mine = ranks.share(tc.user_rows).to(dev)  # this process's rows of each step (all on one process)
    with payload.attached(module) as m:

        def step() -> dict[str, float]:
            idx = torch.from_numpy(rng.integers(0, len(x), tc.user_rows)).to(dev)[mine]
            loss = row_loss(m(x[idx]), y[idx], task, distill=False).mean() * (len(mine) / tc.user_rows)
            optim.update(loss)
            return {"personal": (ranks.sum_tensor(loss.detach()) if ranks.world > 1 else loss).item()}

        losses = run_steps(step, tc.steps, progress, tc.precision, dev)
    return payload.eval(), losses


class SealedArrayRecipe(SealedRecipeBase):
    def train_users(
        self, job: Job[SealedConfig], datasets: list[Dataset], keys: list[np.ndarray], task: str | None,
        first_index: int = 0,
    ) -> tuple[list[SealedUser], str, dict[str, int]]:
        loaded, tc, cfg = job.loaded, job.train, job.mode
        datasets, task = prepare_users(loaded, datasets, None, task)
        dev = resolve_device(job.device)
        module = loaded.module.to(dev).eval()
        spec = payload_spec(module, tc, cfg)
        out = []
        for i, (ds, bits) in enumerate(zip(datasets, keys), first_index):
            tr, val = split(ds, tc.val_fraction, tc.seed + i)
            module.requires_grad_(False)  # the base is frozen: held bf16 during the steps under bf16
            bf16 = tc.precision == "bf16"
            restore = frozen_in_bf16(module, loaded, True) if bf16 else None
            payload, losses = train_payload(module, spec, tr, task, tc, cfg, dev, job.progress, job.ranks)
            if restore is not None:
                restore()
            xv, pv = torch.from_numpy(val.x).to(dev), targets_tensor(val, task).to(dev)
            with torch.no_grad():
                o, b = payload.fold(module)(xv), module(xv)
            out.append(SealedUser(payload.to("cpu"), private_report(o, pv, b, task, losses, job), bits, val))
        module.to("cpu")
        return out, task, {}

    def report_view(self, loaded: LoadedModel) -> torch.nn.Module:
        return loaded.module

    def input_shape(self, loaded: LoadedModel, val: Dataset) -> list:
        return list(val.x.shape[1:])


RECIPE = SealedArrayRecipe()
