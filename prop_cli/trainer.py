"""Fine-tuning a loaded checkpoint with the PRoP objective into a keyed model."""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from prop_adapters import LoadedModel

from . import data as data_mod
from .config import PersonalizeConfig
from .errors import PropError
from .evaluate import user_report
from .keyed import KeyedModel, KeyEncoder, key_codes
from .layers import select_layers
from .objective import Batch, KeySampler, check_user_keys, prop_loss

# A seed stream of its own for evaluation keys, so they cannot replay a caller's seeded user key.
_EVAL_STREAM = 0x5EED_E7A1
# Inputs per forward when caching the original's outputs.
_CHUNK = 8192


@dataclass
class User:
    data: data_mod.Dataset
    key_bits: np.ndarray  # 0/1, the user's key (never stored)


@dataclass
class Personalized:
    keyed: KeyedModel
    original: torch.nn.Module
    task: str
    metrics: list[dict]  # one report per user (evaluate.user_report)
    final_losses: dict[str, float]


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except RuntimeError as e:
        raise PropError(f"--device {name!r} is not a device", "use auto, cpu or cuda[:N]") from e
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise PropError(
            f"--device {name} asked for CUDA, which is not available here",
            "use --device cpu or auto",
        )
    return dev


@torch.no_grad()
def _outputs(module: torch.nn.Module, x: torch.Tensor) -> torch.Tensor:
    return torch.cat([module(x[i : i + _CHUNK]) for i in range(0, len(x), _CHUNK)])


def _targets(ds: data_mod.Dataset, task: str) -> torch.Tensor:
    y = torch.from_numpy(ds.y)
    return y if task == "classification" or y.dim() > 1 else y[:, None]


def _task_of(users: list[User]) -> str:
    tasks = {u.data.task for u in users}
    if len(tasks) != 1:
        raise PropError(
            "the --data files mix float targets and integer labels",
            "give every user the same kind of y",
        )
    return tasks.pop()


def check_compatible(loaded: LoadedModel, ds: data_mod.Dataset, flag: str) -> int:
    """Validate a dataset against the model; returns the model's output size."""
    data_mod.check_features(ds, loaded.input_shape, loaded.source, flag=flag)
    try:
        with torch.no_grad():
            out = loaded.module(torch.from_numpy(ds.x[:1]))
    except Exception as e:  # noqa: BLE001 - any failure here means the inputs do not fit the model
        raise PropError(
            f"{flag} {ds.path}: x of shape {tuple(ds.x.shape[1:])} does not fit the model "
            f"({type(e).__name__}: {str(e).splitlines()[0][:120]})",
            "give inputs of the shape the checkpoint was trained on",
        ) from e
    if ds.y is not None:
        data_mod.check_targets(ds, out.shape[-1], flag=flag)
    return out.shape[-1]


def personalize(
    loaded: LoadedModel,
    users: list[User],
    cfg: PersonalizeConfig,
    general: data_mod.Dataset | None = None,
    device: str = "cpu",
    progress: Callable[[int, dict[str, float]], None] | None = None,
) -> Personalized:
    """Train the keyed model of Eq. 5 with the objective of Eq. 8; the loaded module is updated in place."""
    cfg.validate()
    if not users:
        raise PropError("no user data given", "pass --data and --key-file (or --passphrase)")
    check_user_keys([u.key_bits for u in users], cfg.hamming_radius)
    task = _task_of(users)
    for u in users:
        check_compatible(loaded, u.data, "--data")
    if general is not None:
        check_compatible(loaded, general, "--general-data")
    names = select_layers(loaded.module, cfg.layers, cfg.exclude)

    dev = resolve_device(device)
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    module = loaded.module.to(dev).eval()  # eval: batch-norm statistics and dropout stay the original's
    original = copy.deepcopy(module).requires_grad_(False)

    splits = [data_mod.split(u.data, cfg.val_fraction, cfg.seed + i) for i, u in enumerate(users)]
    ux = [torch.from_numpy(tr.x).to(dev) for tr, _ in splits]
    uy = [_targets(tr, task).to(dev) for tr, _ in splits]
    pool = torch.cat(ux + ([torch.from_numpy(general.x).to(dev)] if general is not None else []))
    pool_targets = _outputs(original, pool)  # distillation targets, computed once

    mods = dict(module.named_modules())
    encoder = KeyEncoder(
        code_bits=len(users[0].key_bits),
        features=[mods[n].in_features for n in names],
        hidden=cfg.encoder_hidden,
        scale=cfg.delta_scale,
    )
    km = KeyedModel(module, encoder, names).to(dev)
    if cfg.freeze_base:
        module.requires_grad_(False)
    params = [p for p in km.parameters() if p.requires_grad]
    opt = torch.optim.Adam(params, lr=cfg.lr, foreach=True)  # one kernel per op, not per tensor
    floor = cfg.lr_floor
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda t: floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * t / cfg.steps))
    )
    user_codes = key_codes(np.stack([u.key_bits for u in users]), cfg.key_encoding).to(dev)
    sampler = KeySampler([u.key_bits for u in users], cfg.hamming_radius, rng)

    # The zero-initialised encoder head and tiny late gradients drive Adam's moments into denormal
    # floats, which made CPU steps ~10x slower; flushing them to zero costs nothing in accuracy.
    flush = torch.set_flush_denormal(True)
    try:
        losses = _train(
            km,
            opt,
            sched,
            cfg,
            rng,
            sampler,
            user_codes,
            ux,
            uy,
            pool,
            pool_targets,
            task,
            progress,
        )
    finally:
        if flush:
            torch.set_flush_denormal(False)
    reports = []
    for i, (u, (_, val)) in enumerate(zip(users, splits)):
        reports.append(
            user_report(
                km,
                original,
                torch.from_numpy(val.x).to(dev),
                _targets(val, task).to(dev),
                u.key_bits,
                cfg.key_encoding,
                task,
                cfg.eval_random_keys,
                np.random.default_rng((cfg.seed, _EVAL_STREAM, i)),
            )
        )
    return Personalized(km, original, task, reports, losses)


def _train(
    km, opt, sched, cfg, rng, sampler, user_codes, ux, uy, pool, pool_targets, task, progress
) -> dict[str, float]:
    losses: dict[str, float] = {}
    for step in range(cfg.steps):
        batch = _batch(cfg, rng, sampler, user_codes, ux, uy, pool, pool_targets)
        deltas = km.layer_deltas(batch.codes, null=1)
        out = km.run_rows(batch.x, deltas, batch.key_index, batch.sample_index)
        loss, losses = prop_loss(out, batch, task, cfg.null_weight)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        if progress is not None:
            progress(step + 1, losses)
    return losses


def _batch(
    cfg: PersonalizeConfig,
    rng: np.random.Generator,
    sampler: KeySampler,
    user_codes: torch.Tensor,
    ux: list[torch.Tensor],
    uy: list[torch.Tensor],
    pool: torch.Tensor,
    pool_targets: torch.Tensor,
) -> Batch:
    """Rows: [user rows | sampled-key fallback rows | null rows]; prop_loss relies on that order."""
    dev = pool.device
    n_users = len(ux)
    per_user = max(1, cfg.user_rows // n_users)
    xs, ys, user_key = [], [], []
    for i in range(n_users):
        idx = torch.from_numpy(rng.integers(0, len(ux[i]), per_user)).to(dev)
        xs.append(ux[i][idx])
        ys.append(uy[i][idx])
        user_key += [i] * per_user
    n_user_rows = per_user * n_users

    fb = torch.from_numpy(rng.integers(0, len(pool), cfg.null_rows)).to(dev)
    sampled = np.concatenate([sampler.neighbours(cfg.neighbour_keys), sampler.random(cfg.random_keys)])
    codes = torch.cat([user_codes, key_codes(sampled, cfg.key_encoding).to(dev)])
    k, s = len(sampled), cfg.samples_per_key
    pick = rng.integers(0, cfg.null_rows, k * s)  # which fallback samples each sampled key sees

    sample_index = np.concatenate(
        [
            np.arange(n_user_rows),
            n_user_rows + pick,
            n_user_rows + np.arange(cfg.null_rows),
        ]
    )
    key_index = np.concatenate(
        [
            np.asarray(user_key),
            n_users + np.repeat(np.arange(k), s),
            np.full(cfg.null_rows, n_users + k),
        ]
    )
    fb_rows = torch.cat([fb[torch.from_numpy(pick).to(dev)], fb])
    return Batch(
        x=torch.cat([*xs, pool[fb]]),
        sample_index=torch.from_numpy(sample_index).to(dev),
        key_index=torch.from_numpy(key_index).to(dev),
        codes=codes,
        user_rows=n_user_rows,
        null_rows=cfg.null_rows,
        user_targets=torch.cat(ys),
        fallback_targets=pool_targets[fb_rows],
    )
