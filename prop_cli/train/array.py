"""Recipe: an array model (one tensor in, one out), unsealed: the keyed model of Eq. 5 trained with the
objective of Eq. 8, base and key encoder together (or the encoder alone with ``--freeze-base``)."""

from __future__ import annotations

import copy
import functools
from collections.abc import Callable

import numpy as np
import torch

from prop_cli.config import UnsealedConfig
from prop_cli.core.device import resolve_device
from prop_cli.core.key_sampling import HARD_STREAM, KeySampler
from prop_cli.core.keyed_model import KeyedModel, KeyEncoder, key_codes, outputs_for_codes
from prop_cli.core.layers import in_width, select_layers
from prop_cli.datasources import Dataset
from prop_cli.fit import split

from .data import outputs, prepare_users, targets_tensor
from .frozen import frozen_in_bf16
from .hardening import antipode_codes, code_negatives, encoder_init, far_codes
from .loop import Optimiser, run_steps
from .objective import Batch, check_user_keys, delta_pull, prop_loss, prop_loss_share, row_loss
from .recipe import Job, Recipe, User
from .report import eval_rng, user_report
from .unsealed import Personalized

# Given inputs each hard-negative candidate key is scored on (``divergence``).
HARD_SAMPLES = 64
# Noisy fallback inputs labelled at a time, and the most memory they may take.
_BANK_ROWS = 8192
_BANK_BYTES = 64 << 20


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
        if k == n:  # all noisy (the default): no given rows to gather (drawing none leaves rng as it was)
            return self._noisy(k, rng)
        idx = torch.from_numpy(rng.integers(0, len(self.x), n - k)).to(self.x.device)
        x, t = self.x[idx], self.targets[idx]
        if k:
            nx, nt = self._noisy(k, rng)
            x, t = torch.cat([x, nx]), torch.cat([t, nt])
        return x, t


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
    cfg: UnsealedConfig,
    user_rows: int,
    rng: np.random.Generator,
    sampler: KeySampler,
    user_codes: torch.Tensor,
    users: UserPool,
    pool: FallbackPool,
    extra_codes: torch.Tensor | None = None,
    far: int = 0,
) -> Batch:
    """One step's rows: [user rows | sampled-key fallback rows | null rows] (prop_loss's order).

    ``extra_codes``: more fallback codes after the sampled keys': the first ``far`` of them --harden's
    antipode codes and the far codes (``hardening``), the rest --harden's code-space negatives;
    each group a fallback term of its own."""
    dev = pool.x.device
    n_users = len(users)
    per_user = max(1, user_rows // n_users)
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
        code_rows=0 if extra_codes is None else (len(extra_codes) - far) * s,
        far_rows=far * s,
    )


def divergence(
    km: KeyedModel, pool: FallbackPool, cfg: UnsealedConfig, task: str, rng: np.random.Generator
) -> Callable[[np.ndarray], np.ndarray]:
    """The hard-negative score (``KeySampler.step``): each key's fallback loss, Eq. 8's own term, on
    ``HARD_SAMPLES`` given inputs drawn afresh per scoring (``rng``: a stream of its own, so scoring
    leaves training's draws as they were)."""

    @torch.no_grad()
    def score(keys: np.ndarray) -> np.ndarray:
        idx = torch.from_numpy(rng.integers(0, len(pool.x), HARD_SAMPLES)).to(pool.x.device)
        x, t = pool.x[idx], pool.targets[idx]
        out = outputs_for_codes(km, x, key_codes(keys, cfg.key_encoding).to(x.device))
        k = len(keys)
        loss = row_loss(out.flatten(0, 1), t.repeat(k, *[1] * (t.dim() - 1)), task, distill=True)
        return loss.reshape(k, -1).mean(1).float().cpu().numpy()

    return score


def personalize(job: Job[UnsealedConfig], users: list[User], general: Dataset | None = None) -> Personalized:
    """Train the keyed model of Eq. 5 with the objective of Eq. 8; the loaded module is updated in place."""
    loaded, tc, cfg = job.loaded, job.train, job.mode.for_kind("array")  # --delta-pull's array default
    cfg.check_key_bits(len(users[0].key_bits))
    check_user_keys([u.key_bits for u in users], cfg.hamming_radius)
    datasets, task = prepare_users(loaded, [u.data for u in users], general, tc.task)
    job.say("setting up: the fallback pool and the key encoder")
    names = select_layers(loaded.module, tc.layers, tc.exclude)

    dev = resolve_device(job.device)
    torch.manual_seed(tc.seed)
    rng = np.random.default_rng(tc.seed)
    module = loaded.module.to(dev).eval()  # eval: batch-norm statistics and dropout stay the original's
    original = copy.deepcopy(module).requires_grad_(False)

    splits = [split(d, tc.val_fraction, tc.seed + i) for i, d in enumerate(datasets)]
    ux = [torch.from_numpy(tr.x).to(dev) for tr, _ in splits]
    uy = [targets_tensor(tr, task).to(dev) for tr, _ in splits]
    given = torch.cat(ux + ([torch.from_numpy(general.x).to(dev)] if general is not None else []))
    pool = FallbackPool(given, original, cfg.fallback_noise, cfg.fallback_sigma)
    user_pool = UserPool(ux, uy)

    mods = dict(module.named_modules())
    with encoder_init(cfg.hardening, tc.seed):
        encoder = KeyEncoder(
            code_bits=len(users[0].key_bits),
            features=[in_width(mods[n]) for n in names],
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
    ranks = job.ranks
    reduce = ranks.sum_gradients if ranks.world > 1 else None
    optim = Optimiser(groups, cfg.lr, tc.steps, tc.lr_floor, reduce=reduce)
    user_codes = key_codes(np.stack([u.key_bits for u in users]), cfg.key_encoding).to(dev)
    keys = [u.key_bits for u in users]
    sampler = KeySampler(keys, cfg.hamming_radius, rng, cfg.hard_negatives, cfg.hard_pool, cfg.hard_every)
    score = divergence(km, pool, cfg, task, np.random.default_rng((tc.seed, HARD_STREAM)))

    hard = cfg.hardening

    def step() -> dict[str, float]:
        sampler.step(score)
        near = code_negatives(user_codes, hard.code_negatives, hard.code_flip_max, hard.code_relax_min, rng)
        # After K1 and K2: --harden's antipode codes, then the far codes (one term; in this order so that
        # the pull's rows are one slice, below), then its code-space negatives (a term of their own: 64 of
        # them had cut the far codes' weight to a fifth).
        n_far = cfg.far_codes + hard.antipode_codes
        if n_far:
            far = far_codes(user_codes, cfg.far_codes, rng)
            anti = antipode_codes(user_codes, hard.antipode_codes, rng)
            near = torch.cat([anti, far, near])
        batch = make_batch(cfg, tc.user_rows, rng, sampler, user_codes, user_pool, pool, near, far=n_far)
        deltas = km.layer_deltas(batch.codes, null=1)
        # Pulled to the no-key model: K1, K2 and the antipode codes, the codes at or beyond a random key's
        # distance; not the codes placed nearer the user's (far codes, --harden's code-space negatives):
        # pulled, they flatten the encoder next to the user's code and drag the user's own scales along
        # (objective.delta_pull).
        n_keys = cfg.neighbour_keys + cfg.random_keys
        sampled = slice(len(users), len(users) + n_keys + hard.antipode_codes)
        pull = cfg.delta_pull * delta_pull(deltas, sampled, of=n_keys + n_far) if cfg.delta_pull else 0.0
        if ranks.world == 1:
            out = km.run_rows(batch.x, deltas, batch.key_index, batch.sample_index)
            loss, losses = prop_loss(out, batch, task, cfg.null_weight, cfg.key_weight)
            optim.update(loss + pull)
            return losses
        # Data parallel: this process's share of the step's rows; the gradients are summed over processes.
        rows = ranks.share(len(batch.key_index)).to(dev)
        out = km.run_rows(batch.x, deltas, batch.key_index[rows], batch.sample_index[rows])
        loss, parts = prop_loss_share(out, batch, rows, task, cfg.null_weight, cfg.key_weight)
        optim.update(loss + pull / ranks.world)  # every process's share of the encoder-only term
        parts = ranks.sum_tensor(parts)
        return {"personal": parts[0].item(), "fallback": parts[1].item(), "null": parts[2].item()}

    # --freeze-base under --precision bf16: the frozen matrices held bf16 during the steps (frozen.py).
    restore = frozen_in_bf16(module, loaded, True) if tc.precision == "bf16" else None
    losses = run_steps(step, tc.steps, job.progress, tc.precision, dev)
    if restore is not None:
        restore()
    optim = None  # Adam's state freed before the report
    reports = [
        user_report(
            km,
            original,
            torch.from_numpy(val.x).to(dev),
            targets_tensor(val, task).to(dev),
            u.key_bits,
            cfg.key_encoding,
            task,
            tc.eval_random_keys,
            eval_rng(tc.seed, i),
        )
        for i, (u, (_, val)) in enumerate(zip(users, splits))
    ]
    return Personalized(
        km, original, task, reports, losses, loaded=loaded, cfg=cfg,
        input_shape=list(datasets[0].x.shape[1:]), users=len(users), keys=[u.key_bits for u in users],
    )  # fmt: skip


class ArrayRecipe(Recipe[UnsealedConfig]):
    def personalize(
        self, job: Job[UnsealedConfig], users: list[User], general: Dataset | None = None
    ) -> Personalized:
        return personalize(job, users, general)


RECIPE = ArrayRecipe()
