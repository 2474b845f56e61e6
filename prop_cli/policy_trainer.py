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
from dataclasses import replace

import numpy as np
import torch

from prop_adapters import LoadedModel

from .batch_axes import probe_batch_axes
from .config import PersonalizeConfig
from .datasources import Dataset
from .errors import PropError
from .evaluate import outputs_report
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
    return torch.cat(
        [policy.chunk(_rows(batch, torch.arange(i, min(n, i + _CHUNK)))) for i in range(0, n, _CHUNK)]
    )


def cosine(cfg: PersonalizeConfig):
    """The learning-rate factor at step t: cosine decay from 1 to ``lr_floor`` over the run."""
    floor, steps = cfg.lr_floor, cfg.steps
    return lambda t: floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * t / steps))


class PolicyTrainer:
    """The state of one personalize run and its step (kept apart so benchmarks time exactly this step)."""

    def __init__(
        self, loaded: LoadedModel, users: list, cfg: PersonalizeConfig, general: Dataset | None
    ) -> None:
        policy = self.policy = loaded.policy
        cfg.validate(key_bits=len(users[0].key_bits))
        check_user_keys([u.key_bits for u in users], cfg.hamming_radius)
        self.cfg, self.users = cfg, users
        module = self.module = loaded.module
        names = select_layers(module, cfg.layers or policy.default_layers, cfg.exclude)
        torch.manual_seed(cfg.seed)
        self.rng = rng = np.random.default_rng(cfg.seed)

        self.splits = [_split(policy.batches(u.data, "--data"), cfg.val_fraction) for u in users]
        self.pool = [tr for tr, _ in self.splits]
        fb_parts = self.pool + ([policy.batches(general, "--general-data")] if general is not None else [])
        self.fb = {k: torch.cat([p[k] for p in fb_parts]) for k in [*policy.input_features, "episode_index"]}
        self.original = copy.deepcopy(module).requires_grad_(False).eval()
        self.original_policy = type(policy)(self.original, policy.pre, policy.post)
        self.targets = _chunks(self.original_policy, self.fb)

        mods = dict(module.named_modules())
        features = [mods[n].in_features for n in names]
        encoder = KeyEncoder(len(users[0].key_bits), features, cfg.encoder_hidden, cfg.delta_scale)
        self.km = KeyedModel(module, encoder, names)
        self.km.batch_axis = probe_batch_axes(
            module, names, lambda b: policy.chunk(policy.example(b, self.fb)), f"the policy {loaded.source}"
        )
        if cfg.freeze_base:
            module.requires_grad_(False)
        base = [p for p in module.parameters() if p.requires_grad]
        groups = [{"params": list(encoder.parameters())}]
        if base:
            groups.append({"params": base, "lr": cfg.lr * cfg.base_lr_scale})
        self.opt = torch.optim.Adam(groups, lr=cfg.lr)
        self.sched = torch.optim.lr_scheduler.LambdaLR(self.opt, cosine(cfg))
        self.params = [p for g in groups for p in g["params"]]
        self.user_codes = key_codes(np.stack([u.key_bits for u in users]), cfg.key_encoding)
        self.sampler = KeySampler([u.key_bits for u in users], cfg.hamming_radius, rng)
        self.per_user = max(1, cfg.user_rows // len(users))

    def step(self) -> dict[str, float]:
        cfg, km, rng, policy = self.cfg, self.km, self.rng, self.policy
        # User rows: the policy's own loss, each user's rows under that user's key.
        picks = [
            torch.from_numpy(rng.integers(0, len(tr["episode_index"]), self.per_user)) for tr in self.pool
        ]
        ub = {k: torch.cat([_rows(tr, p)[k] for tr, p in zip(self.pool, picks)]) for k in self.pool[0]}
        user_of_row = torch.arange(len(self.users)).repeat_interleave(self.per_user)
        d_user = [d.index_select(0, user_of_row) for d in km.layer_deltas(self.user_codes)]
        personal = km.call_rows(d_user, policy.loss, ub)
        # Fallback rows: null rows, then each sampled key on samples_per_key of the same frames.
        sampled = np.concatenate(
            [self.sampler.neighbours(cfg.neighbour_keys), self.sampler.random(cfg.random_keys)]
        )
        gi = torch.from_numpy(rng.integers(0, len(self.targets), cfg.null_rows))
        k_rows = torch.arange(len(sampled)).repeat_interleave(cfg.samples_per_key)
        idx = torch.cat([gi, gi[torch.from_numpy(rng.integers(0, cfg.null_rows, len(k_rows)))]])
        deltas = km.layer_deltas(key_codes(sampled, cfg.key_encoding) if len(sampled) else None, null=1)
        key_of_row = torch.cat([torch.full((len(gi),), len(sampled)), k_rows])
        pred = km.call_rows(
            [d.index_select(0, key_of_row) for d in deltas], policy.chunk, _rows(self.fb, idx)
        )
        per_row = (pred - self.targets[idx]).abs().flatten(1).mean(1)
        null = per_row[: len(gi)].mean()
        keyed = per_row[len(gi) :].mean() if len(k_rows) else per_row.new_zeros(())
        loss = personal + keyed + cfg.null_weight * null
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(self.params, CLIP)
        self.opt.step()
        self.sched.step()
        return {"personal": personal.item(), "fallback": keyed.item(), "null": null.item()}


def check_cpu(device: str) -> None:
    if device not in ("cpu", "auto"):
        raise PropError(
            f"--device {device}: LeRobot policies train on the CPU in this version", "drop --device"
        )


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

    check_cpu(device)
    t = PolicyTrainer(loaded, users, cfg, general)
    flush = torch.set_flush_denormal(True)  # as trainer.py: denormal Adam moments stall CPU steps
    losses: dict[str, float] = {}
    try:
        for step in range(cfg.steps):
            losses = t.step()
            if progress is not None:
                progress(step + 1, losses)
    finally:
        if flush:
            torch.set_flush_denormal(False)
    t.module.eval()
    reports = [
        chunk_report(t.km, t.policy, t.original_policy, val, u.key_bits, cfg,
                     np.random.default_rng((cfg.seed, _EVAL_STREAM, i)))
        for i, (u, (_, val)) in enumerate(zip(users, t.splits))
    ]  # fmt: skip
    return Personalized(t.km, t.original, "regression", reports, losses)


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
        return torch.stack(
            [km.call_rows([d[i : i + 1] for d in every], _chunks, policy, val) for i in range(len(codes))]
        )

    enc = cfg.key_encoding
    o_user = under(key_codes(bits, enc))
    o_rand = under(key_codes(random_keys(cfg.eval_random_keys, len(bits), rng, exclude=bits), enc))
    o_ham = under(key_codes(one_bit_neighbours(bits), enc))
    return outputs_report(b, p, "regression", o_user[0], under(None), o_rand, o_ham)


def train_policy_payloads(
    loaded: LoadedModel,
    datasets: list[Dataset],
    keys: list[np.ndarray],
    cfg: PersonalizeConfig,
    device: str = "cpu",
    progress=None,
    first_index: int = 0,
) -> tuple[list, dict[str, int]]:
    """Sealed policies (`--seal`): each user's payload trained on their frames alone with the policy's
    own loss, the base frozen (it stays the original). No fallback terms: a wrong key opens no record
    and the original runs. Returns the users (``sealed.SealedUser``, validation as flat chunks) and the
    keyed layers' batch axes (the audit keys the public base at those layers)."""
    check_cpu(device)
    from .payload import Payload
    from .policy_view import flat_chunks
    from .sealed import SealedUser, payload_spec

    policy, module = loaded.policy, loaded.module.eval()
    layers = cfg.layers or policy.default_layers
    spec = payload_spec(module, replace(cfg, layers=layers))
    names = [x["name"] for x in spec.layers]
    splits = [_split(policy.batches(d, "--data"), cfg.val_fraction) for d in datasets]
    axes = probe_batch_axes(
        module, names, lambda b: policy.chunk(policy.example(b, splits[0][0])), f"the policy {loaded.source}"
    )
    module.requires_grad_(False)
    out = []
    for i, ((tr, val), bits) in enumerate(zip(splits, keys), first_index):
        torch.manual_seed(cfg.seed + i)
        rng = np.random.default_rng((cfg.seed, i))
        payload = Payload(spec, torch.Generator().manual_seed(cfg.seed + i))
        opt = torch.optim.Adam(payload.parameters(), lr=cfg.payload_lr)
        sched = torch.optim.lr_scheduler.LambdaLR(opt, cosine(cfg))
        losses: dict[str, float] = {}
        n = len(tr["episode_index"])
        with payload.attached(module):
            for step in range(cfg.steps):
                loss = policy.loss(_rows(tr, torch.from_numpy(rng.integers(0, n, cfg.user_rows))))
                opt.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(payload.parameters(), CLIP)
                opt.step()
                sched.step()
                losses = {"personal": loss.item()}
                if progress is not None:
                    progress(step + 1, losses)
        module.eval()
        payload.eval()
        folded = type(policy)(payload.fold(module), policy.pre, policy.post)
        b, o, p = _chunks(policy, val), _chunks(folded, val), val["action"]
        private = {
            "personalization": personalization(o, p, b, "regression"),
            "user_leakage": leakage(o[None], p, b, "regression").item(),
            "samples": int(len(p)),
            "final_losses": losses,
            "config": cfg.to_dict(),
        }
        flat_val = flat_chunks(policy, val, datasets[i - first_index].path)
        out.append(SealedUser(payload, private, bits, flat_val))
    return out, axes
