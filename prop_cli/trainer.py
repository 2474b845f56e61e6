"""Fine-tuning a loaded checkpoint with the PRoP objective into a keyed model."""

from __future__ import annotations

import copy
import functools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from prop_adapters import LoadedModel

from . import data as data_mod
from .config import PersonalizeConfig
from .datasources import Dataset
from .errors import PropError
from .evaluate import user_report
from .hardening import code_negatives, encoder_init
from .keyed import KeyedModel, KeyEncoder, key_codes
from .keyspace import KeySampler
from .layers import select_layers
from .objective import Batch, check_user_keys, prop_loss
from .optim import Adam, cosine_lr

# A seed stream of its own for evaluation keys, so they cannot replay a caller's seeded user key.
_EVAL_STREAM = 0x5EED_E7A1
# Inputs per forward when caching the original's outputs.
_CHUNK = 8192
# Noisy fallback inputs labelled at a time, and the most memory they may take.
_BANK_ROWS = 8192
_BANK_BYTES = 64 << 20

Progress = Callable[[int, dict[str, float]], None]  # (step, latest losses)


@dataclass
class User:
    data: Dataset
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
def outputs(module: torch.nn.Module, x: torch.Tensor) -> torch.Tensor:
    """The module's outputs on many inputs, in chunks."""
    return torch.cat([module(x[i : i + _CHUNK]) for i in range(0, len(x), _CHUNK)])


def targets_tensor(ds: Dataset, task: str) -> torch.Tensor:
    """y as the loss wants it: labels (N,), or float targets (N, d)."""
    y = torch.from_numpy(ds.y)
    return y if task == "classification" or y.dim() > 1 else y[:, None]


class FallbackPool:
    """The inputs the no-key, random-key and neighbour-key rows are trained on, and their targets.

    The given inputs (users' training data, ``--general-data``) are labelled by the original once. A
    share ``noise`` of each draw is a given input plus Gaussian noise of ``sigma`` per-feature standard
    deviations, labelled by the original: the no-key model then matches the original around and
    between the data points too, not only on them. Noisy inputs are made and labelled a bank at a time
    (up to ``_BANK_ROWS``) and each is used once: one large forward instead of a small one per step,
    which on a small model cost as much as a tenth of the step.
    """

    def __init__(self, x: torch.Tensor, original: torch.nn.Module, noise: float, sigma: float) -> None:
        self.x = x
        self.original = original
        self.targets = outputs(original, x)
        self.noise = noise
        self.scale = sigma * x.std(0, keepdim=True) if len(x) > 1 else torch.zeros_like(x[:1])
        self._bank: tuple[torch.Tensor, torch.Tensor] | None = None
        self._used = 0

    def _noisy(self, k: int, rng: np.random.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        if self._bank is None or self._used + k > len(self._bank[0]):
            per_row = max(1, self.x[0].numel() * self.x.element_size())
            rows = max(k, min(_BANK_ROWS, _BANK_BYTES // per_row) // k * k)
            idx = torch.from_numpy(rng.integers(0, len(self.x), rows)).to(self.x.device)
            eps = rng.standard_normal((rows, *self.x.shape[1:])).astype(np.float32)
            bank_x = self.x[idx] + self.scale * torch.from_numpy(eps).to(self.x.device)
            self._bank, self._used = (bank_x, outputs(self.original, bank_x)), 0
        x, t = (b[self._used : self._used + k] for b in self._bank)
        self._used += k
        return x, t

    def draw(self, n: int, rng: np.random.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        k = int(round(self.noise * n))
        idx = torch.from_numpy(rng.integers(0, len(self.x), n - k)).to(self.x.device)
        x, t = self.x[idx], self.targets[idx]
        if k:
            nx, nt = self._noisy(k, rng)
            x, t = torch.cat([x, nx]), torch.cat([t, nt])
        return x, t


def _prepare(loaded: LoadedModel, users: list[User], general: Dataset | None, task: str | None):
    """Users' data checked against the model, with one task for all; general inputs checked too."""
    prepared = [data_mod.prepare(loaded, u.data, "--data", task) for u in users]
    tasks = {t for _, t in prepared}
    if len(tasks) != 1:
        raise PropError(
            "the --data files hold different kinds of y (class labels and float targets)",
            "give every user the same kind of y, or set --task",
        )
    if general is not None:
        data_mod.output_width(loaded, general, "--general-data")
    return [d for d, _ in prepared], tasks.pop()


def personalize(
    loaded: LoadedModel,
    users: list[User],
    cfg: PersonalizeConfig,
    general: Dataset | None = None,
    device: str = "cpu",
    progress: Progress | None = None,
) -> Personalized:
    """Train the keyed model of Eq. 5 with the objective of Eq. 8; the loaded module is updated in place."""
    if not users:
        raise PropError("no user data given", "pass --data and --key-file (or --passphrase)")
    if loaded.policy is not None:  # a policy with its own loss (LeRobot): prop_cli.policy_trainer
        from .policy_trainer import personalize_policy

        return personalize_policy(loaded, users, cfg, general, device, progress)
    cfg.validate(key_bits=len(users[0].key_bits))
    check_user_keys([u.key_bits for u in users], cfg.hamming_radius)
    datasets, task = _prepare(loaded, users, general, cfg.task)
    names = select_layers(loaded.module, cfg.layers, cfg.exclude)

    dev = resolve_device(device)
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    module = loaded.module.to(dev).eval()  # eval: batch-norm statistics and dropout stay the original's
    original = copy.deepcopy(module).requires_grad_(False)

    splits = [data_mod.split(d, cfg.val_fraction, cfg.seed + i) for i, d in enumerate(datasets)]
    ux = [torch.from_numpy(tr.x).to(dev) for tr, _ in splits]
    uy = [targets_tensor(tr, task).to(dev) for tr, _ in splits]
    given = torch.cat(ux + ([torch.from_numpy(general.x).to(dev)] if general is not None else []))
    pool = FallbackPool(given, original, cfg.fallback_noise, cfg.fallback_sigma)
    user_pool = UserPool(ux, uy)

    mods = dict(module.named_modules())
    with encoder_init(cfg):
        encoder = KeyEncoder(
            code_bits=len(users[0].key_bits),
            features=[mods[n].in_features for n in names],
            hidden=cfg.encoder_hidden,
            scale=cfg.delta_scale,
        )
    km = KeyedModel(module, encoder, names).to(dev)
    if cfg.freeze_base:
        module.requires_grad_(False)
    groups = [{"params": list(encoder.parameters())}]
    base = [p for p in module.parameters() if p.requires_grad]
    if base:
        groups.append({"params": base, "lr": cfg.lr * cfg.base_lr_scale})
    opt = Adam(groups, lr=cfg.lr)  # torch.optim's update, without its 2 s torch._dynamo import
    user_codes = key_codes(np.stack([u.key_bits for u in users]), cfg.key_encoding).to(dev)
    sampler = KeySampler([u.key_bits for u in users], cfg.hamming_radius, rng)

    # The zero-initialised encoder head and tiny late gradients drive Adam's moments into denormal
    # floats, which made CPU steps ~10x slower; flushing them to zero costs nothing in accuracy.
    flush = torch.set_flush_denormal(True)
    try:
        losses: dict[str, float] = {}
        for step in range(cfg.steps):
            near = code_negatives(user_codes, cfg.code_negatives, cfg.code_flip_max, cfg.code_relax_min, rng)
            batch = make_batch(cfg, rng, sampler, user_codes, user_pool, pool, near)
            deltas = km.layer_deltas(batch.codes, null=1)
            out = km.run_rows(batch.x, deltas, batch.key_index, batch.sample_index)
            loss, losses = prop_loss(out, batch, task, cfg.null_weight)
            opt.zero_grad()
            loss.backward()
            opt.step()
            opt.set_lr_factor(cosine_lr(1.0, step + 1, cfg.steps, cfg.lr_floor))
            if progress is not None:
                progress(step + 1, losses)
    finally:
        if flush:
            torch.set_flush_denormal(False)
    reports = [
        user_report(
            km,
            original,
            torch.from_numpy(val.x).to(dev),
            targets_tensor(val, task).to(dev),
            u.key_bits,
            cfg.key_encoding,
            task,
            cfg.eval_random_keys,
            np.random.default_rng((cfg.seed, _EVAL_STREAM, i)),
        )
        for i, (u, (_, val)) in enumerate(zip(users, splits))
    ]
    return Personalized(km, original, task, reports, losses)


class UserPool:
    """All users' training rows in one tensor, so a step draws every user's rows with one gather."""

    def __init__(self, ux: list[torch.Tensor], uy: list[torch.Tensor]) -> None:
        self.x, self.y = torch.cat(ux), torch.cat(uy)
        self.lengths = np.array([len(x) for x in ux])
        self.starts = np.concatenate([[0], np.cumsum(self.lengths)[:-1]])

    def __len__(self) -> int:
        return len(self.lengths)

    def draw(self, per_user: int, rng: np.random.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """``per_user`` rows of each user, user by user."""
        idx = np.repeat(self.starts, per_user) + rng.integers(0, np.repeat(self.lengths, per_user))
        idx = torch.from_numpy(idx).to(self.x.device)
        return self.x[idx], self.y[idx]


@functools.lru_cache(maxsize=8)
def _layout(n_users: int, per_user: int, keys: int, samples: int, null_rows: int) -> tuple[np.ndarray, ...]:
    """A step's fixed row layout: key_index, and sample_index with the sampled keys' rows left to fill."""
    u = n_users * per_user
    key_index = np.concatenate(
        [np.repeat(np.arange(n_users), per_user), n_users + np.repeat(np.arange(keys), samples),
         np.full(null_rows, n_users + keys)]
    )  # fmt: skip
    sample_index = np.concatenate(
        [np.arange(u), np.zeros(keys * samples, np.int64), u + np.arange(null_rows)]
    )
    return key_index, sample_index


def make_batch(
    cfg: PersonalizeConfig,
    rng: np.random.Generator,
    sampler: KeySampler,
    user_codes: torch.Tensor,
    users: UserPool,
    pool: FallbackPool,
    extra_codes: torch.Tensor | None = None,
) -> Batch:
    """One step's rows: [user rows | sampled-key fallback rows | null rows] (prop_loss's order).

    ``extra_codes``: more fallback codes (code-space negatives of --harden), after the sampled keys'."""
    dev = pool.x.device
    n_users = len(users)
    per_user = max(1, cfg.user_rows // n_users)
    ux, uy = users.draw(per_user, rng)
    n_user_rows = per_user * n_users

    fb_x, fb_t = pool.draw(cfg.null_rows, rng)
    sampled = np.concatenate([sampler.neighbours(cfg.neighbour_keys), sampler.random(cfg.random_keys)])
    codes = torch.cat([user_codes, key_codes(sampled, cfg.key_encoding).to(dev)])
    if extra_codes is not None:
        codes = torch.cat([codes, extra_codes.to(dev)])
    k, s = len(codes) - n_users, cfg.samples_per_key
    pick = rng.integers(0, cfg.null_rows, k * s)  # which fallback samples each sampled key sees

    key_index, sample_index = _layout(n_users, per_user, k, s, cfg.null_rows)
    sample_index = sample_index.copy()
    sample_index[n_user_rows : n_user_rows + k * s] = n_user_rows + pick
    pick_t = torch.from_numpy(pick).to(dev)
    return Batch(
        x=torch.cat([ux, fb_x]),
        sample_index=torch.from_numpy(sample_index).to(dev),
        key_index=torch.from_numpy(key_index.copy()).to(dev),  # the cached layout stays untouched
        codes=codes,
        user_rows=n_user_rows,
        null_rows=cfg.null_rows,
        user_targets=uy,
        fallback_targets=torch.cat([fb_t[pick_t], fb_t]),
    )
