"""Eq. 8 for policies that bring their own loss (LeRobot ACT): the trainer behind `prop personalize`.

User term: the policy's own training loss (ACT: L1 on the action chunk, padding masked, plus its
VAE's KL) on the user's frames, every row under the user's key. Fallback terms (the null key, weighted
by ``null_weight``; K1 Hamming neighbours and K2 random keys): L1 between the keyed policy's deployed
chunk and the frozen original's chunk on general observations, the targets computed once
("distill"). Measured against the policy's loss on general data and against relabelled actions, the
distilled fallback kept wrong keys at the base's closed-loop success and the no-key chunk closest to
the original's (examples/RESULTS.md, "LeRobot ACT").

Two forwards per step: the user rows in training mode (the policy's loss needs its training path),
the fallback rows in eval mode (the path the policy is deployed with). Rows carry their own keys.
"""

from __future__ import annotations

import copy
import math

import numpy as np
import torch

from prop_adapters import LoadedModel

from .batch_axes import probe_batch_axes
from .config import PersonalizeConfig
from .datasources import Dataset
from .errors import PropError
from .evaluate import _group
from .keyed import KeyedModel, KeyEncoder, key_codes
from .keyspace import KeySampler, one_bit_neighbours, random_keys
from .layers import select_layers
from .metrics import leakage, personalization
from .objective import check_user_keys

_EVAL_STREAM = 0x5EED_E7A1  # the trainer's stream for evaluation keys (same role as in trainer.py)
_CHUNK = 256  # rows per forward when caching the original's chunks
CLIP = 10.0  # gradient-norm clip, as LeRobot's training loop


def _rows(batch: dict[str, torch.Tensor], idx: torch.Tensor) -> dict[str, torch.Tensor]:
    return {k: v[idx] for k, v in batch.items()}


def _split(batch: dict[str, torch.Tensor], fraction: float) -> tuple[dict, dict]:
    """Hold out the last ``fraction`` of the episodes (whole episodes: frames of one are correlated)."""
    eps = batch["episode_index"].unique()
    n_val = min(len(eps) - 1, max(1, round(fraction * len(eps))))
    if n_val < 1:
        raise PropError("--data has one episode; prop holds out whole episodes", "record at least two")
    val = torch.isin(batch["episode_index"], eps[-n_val:])
    return _rows(batch, ~val), _rows(batch, val)


@torch.no_grad()
def _chunks(policy, batch: dict[str, torch.Tensor]) -> torch.Tensor:
    n = len(batch["episode_index"])
    return torch.cat([policy.chunk(_rows(batch, torch.arange(i, min(n, i + _CHUNK)))) for i in range(0, n, _CHUNK)])


def personalize_policy(
    loaded: LoadedModel,
    users: list,
    cfg: PersonalizeConfig,
    general: Dataset | None = None,
    device: str = "cpu",
    progress=None,
):
    """Train the keyed policy (Eq. 5) with Eq. 8; returns trainer.Personalized. CPU only in this version."""
    from .trainer import Personalized

    policy = loaded.policy
    if device not in ("cpu", "auto"):
        raise PropError(f"--device {device}: LeRobot policies are trained on the CPU in this version", "drop --device")
    cfg.validate(key_bits=len(users[0].key_bits))
    check_user_keys([u.key_bits for u in users], cfg.hamming_radius)
    module = loaded.module
    names = select_layers(module, cfg.layers or policy.default_layers, cfg.exclude)
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)

    splits = [_split(policy.batches(u.data, "--data"), cfg.val_fraction) for u in users]
    pool = [tr for tr, _ in splits]
    if general is not None:
        pool.append(policy.batches(general, "--general-data"))
    obs = list(policy.input_features) + ["episode_index"]
    fb = {k: torch.cat([p[k] for p in pool]) for k in obs}
    original = copy.deepcopy(module).requires_grad_(False).eval()
    original_policy = type(policy)(original, policy.pre, policy.post)
    targets = _chunks(original_policy, fb)

    mods = dict(module.named_modules())
    encoder = KeyEncoder(len(users[0].key_bits), [mods[n].in_features for n in names], cfg.encoder_hidden, cfg.delta_scale)
    km = KeyedModel(module, encoder, names)
    km.batch_axis = probe_batch_axes(
        module, names, lambda b: policy.chunk(policy.example(b, fb)), f"the policy {loaded.source}"
    )
    if cfg.freeze_base:
        module.requires_grad_(False)
    base = [p for p in module.parameters() if p.requires_grad]
    groups = [{"params": list(encoder.parameters())}]
    if base:
        groups.append({"params": base, "lr": cfg.lr * cfg.base_lr_scale})
    opt = torch.optim.Adam(groups, lr=cfg.lr)
    floor = cfg.lr_floor
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda t: floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * t / cfg.steps))
    )
    params = [p for g in groups for p in g["params"]]
    user_codes = key_codes(np.stack([u.key_bits for u in users]), cfg.key_encoding)
    sampler = KeySampler([u.key_bits for u in users], cfg.hamming_radius, rng)
    per_user = max(1, cfg.user_rows // len(users))
    n_fb = len(targets)

    flush = torch.set_flush_denormal(True)  # as trainer.py: denormal Adam moments stall CPU steps
    losses: dict[str, float] = {}
    try:
        for step in range(cfg.steps):
            # User rows: the policy's own loss, each user's rows under that user's key.
            picks = [torch.from_numpy(rng.integers(0, len(tr["episode_index"]), per_user)) for tr in pool[: len(users)]]
            ub = {k: torch.cat([_rows(pool[i], p)[k] for i, p in enumerate(picks)]) for k in pool[0]}
            user_of_row = torch.arange(len(users)).repeat_interleave(per_user)
            d_user = [d.index_select(0, user_of_row) for d in km.layer_deltas(user_codes)]
            personal = km.call_rows(d_user, policy.loss, ub)
            # Fallback rows: null rows, then each sampled key on samples_per_key of the same frames.
            sampled = np.concatenate([sampler.neighbours(cfg.neighbour_keys), sampler.random(cfg.random_keys)])
            gi = torch.from_numpy(rng.integers(0, n_fb, cfg.null_rows))
            k_rows = torch.arange(len(sampled)).repeat_interleave(cfg.samples_per_key)
            k_idx = gi[torch.from_numpy(rng.integers(0, cfg.null_rows, len(k_rows)))]
            idx = torch.cat([gi, k_idx])
            codes = key_codes(sampled, cfg.key_encoding) if len(sampled) else None
            deltas = km.layer_deltas(codes, null=1)
            key_of_row = torch.cat([torch.full((len(gi),), len(sampled)), k_rows])
            d_fb = [d.index_select(0, key_of_row) for d in deltas]
            pred = km.call_rows(d_fb, policy.chunk, _rows(fb, idx))
            per_row = (pred - targets[idx]).abs().flatten(1).mean(1)
            null = per_row[: len(gi)].mean()
            keyed = per_row[len(gi) :].mean() if len(k_rows) else per_row.new_zeros(())
            loss = personal + keyed + cfg.null_weight * null
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(params, CLIP)
            opt.step()
            sched.step()
            losses = {"personal": personal.item(), "fallback": keyed.item(), "null": null.item()}
            if progress is not None:
                progress(step + 1, losses)
    finally:
        if flush:
            torch.set_flush_denormal(False)
    module.eval()
    reports = [
        chunk_report(km, policy, original_policy, val, u.key_bits, cfg, np.random.default_rng((cfg.seed, _EVAL_STREAM, i)))
        for i, (u, (_, val)) in enumerate(zip(users, splits))
    ]
    return Personalized(km, original, "regression", reports, losses)


@torch.no_grad()
def chunk_report(km, policy, original, val: dict, bits: np.ndarray, cfg: PersonalizeConfig, rng) -> dict:
    """personalization, leakage and fidelity (docs/metrics.md) on held-out frames' action chunks.

    ``b`` = the original's chunk, ``p`` = the user's recorded chunk (normalised units; padded steps
    repeat the episode's last action, as LeRobot pads), ``o`` = the keyed policy's chunk under a key.
    """
    p, b = val["action"], _chunks(original, val)

    def under(codes: torch.Tensor | None) -> torch.Tensor:
        if codes is None:
            return _chunks(policy, val)[None]
        every = km.layer_deltas(codes)
        return torch.stack([km.call_rows([d[i : i + 1] for d in every], _chunks, policy, val) for i in range(len(codes))])

    enc = cfg.key_encoding
    o_user = under(key_codes(bits, enc))
    o_rand = under(key_codes(random_keys(cfg.eval_random_keys, len(bits), rng, exclude=bits), enc))
    o_ham = under(key_codes(one_bit_neighbours(bits), enc))
    return {
        "samples": int(len(p)),
        "personalization": personalization(o_user[0], p, b, "regression"),
        "user_leakage": leakage(o_user, p, b, "regression").item(),
        "null": _group(under(None), p, b, "regression"),
        "random": _group(o_rand, p, b, "regression"),
        "hamming1": _group(o_ham, p, b, "regression"),
    }
