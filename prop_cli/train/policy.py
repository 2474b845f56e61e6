"""Recipe: a policy that brings its own loss (LeRobot ACT, Diffusion), unsealed: Eq. 8 with the policy's
own terms, which the policy protocol (``PolicyProtocol``) supplies.

User term: the policy's own training loss (ACT: L1 on the action chunk, padding masked, plus its
VAE's KL; Diffusion: its noise-prediction MSE) on the user's frames, every row under the user's key.
Fallback terms (the null key, weighted by ``null_weight``; K1 Hamming neighbours and K2 random keys)
distil the frozen original on general observations ("distill"): ACT's deployed chunk, L1, the targets
computed once; Diffusion's denoiser on the same (observation, x_t, t) rows, MSE, the original run on
each step's rows. Measured against the policy's loss on general data and against relabelled actions,
the distilled fallback kept wrong keys at the base's closed-loop success and the no-key chunk closest
to the original's (examples/RESULTS.md, "LeRobot ACT").

Two forwards per step: the user rows in training mode (the policy's loss needs its training path),
the fallback rows in eval mode (the path the policy is deployed with). Rows carry their own keys.

On several processes (`accelerate launch`, ``distributed``) each computes its share of both terms'
rows, its part of the policy's loss scaled by its rows' share of the loss's normaliser
(``loss_parts``), and the gradients are summed. What the policy draws inside its forward (dropout,
noise, time) is drawn per row (``row_noise``), so one process and several train the same model.
"""

from __future__ import annotations

import contextlib
import copy

import numpy as np
import torch

from prop_adapters import LoadedModel
from prop_cli.config import PersonalizeConfig
from prop_cli.core.batch_axes import probe_batch_axes
from prop_cli.core.device import resolve_device
from prop_cli.core.key_sampling import KeySampler, one_bit_neighbours, random_keys
from prop_cli.core.keyed_model import KeyedModel, KeyEncoder, key_codes
from prop_cli.core.layers import in_width, select_layers
from prop_cli.datasources import Dataset
from prop_cli.errors import PropError

from .distributed import Ranks
from .loop import Optimiser, run_steps
from .objective import check_user_keys
from .recipe import Job, Recipe, User
from .report import eval_rng, outputs_report
from .row_noise import RowNoise
from .unsealed import Personalized

_CHUNK = 256  # rows per forward when caching the original's chunks
CLIP = 10.0  # gradient-norm clip, as LeRobot's training loop


def rows(batch: dict[str, torch.Tensor], idx: torch.Tensor) -> dict[str, torch.Tensor]:
    return {k: v[idx] for k, v in batch.items()}


def split_episodes(batch: dict[str, torch.Tensor], fraction: float) -> tuple[dict, dict]:
    """Hold out the last ``fraction`` of the episodes (whole episodes: frames of one are correlated)."""
    eps = batch["episode_index"].unique()
    n_val = min(len(eps) - 1, max(1, round(fraction * len(eps))))
    if n_val < 1:
        raise PropError("--data has one episode; prop holds out whole episodes", "record at least two")
    val = torch.isin(batch["episode_index"], eps[-n_val:])
    return rows(batch, ~val), rows(batch, val)


@torch.no_grad()
def chunks(policy, batch: dict[str, torch.Tensor]) -> torch.Tensor:
    """The policy's deployed chunk for every frame of ``batch``, a few hundred frames per forward."""
    n = len(batch["episode_index"])
    return torch.cat(
        [policy.chunk(rows(batch, torch.arange(i, min(n, i + _CHUNK)))) for i in range(0, n, _CHUNK)]
    )


def row_noise(
    policy, forward, seed: tuple[int, ...], module: torch.nn.Module, ranks: Ranks
) -> RowNoise | None:  # fmt: skip
    """The per-row draws of the policy's training forward (``row_noise``); None where it draws
    nothing. A policy whose draws cannot be made per row trains on one process only."""
    noise, why = RowNoise.probe(forward, seed, module)
    if why is not None and ranks.world > 1:
        raise PropError(
            f"{ranks.world} processes: the policy {type(policy).__name__} draws random numbers inside its "
            f"loss that prop cannot draw per row ({why}), so the processes would train on other noise",
            "run this personalize as one process (without accelerate launch)",
        )
    return noise


def drawn(
    noise: RowNoise | None, step: int, ids: torch.Tensor, total: int
) -> contextlib.AbstractContextManager:
    """The context a step's forward over rows ``ids`` (of ``total``) runs in."""
    return contextlib.nullcontext() if noise is None else noise.rows(step, ids, total)


def weighted(parts: list[tuple[torch.Tensor, torch.Tensor]], ranks: Ranks) -> torch.Tensor:
    """The policy's loss parts (``PolicyProtocol.loss_parts``) on this process's rows, each scaled by
    its rows' share of the step's weight: summed over the processes, the whole step's loss."""
    share = ranks.weight(torch.stack([w.sum() for _, w in parts]).float())
    return sum(v * s for (v, _), s in zip(parts, share))


def to_device(batch: dict[str, torch.Tensor], device: torch.device) -> dict[str, torch.Tensor]:
    return {k: v.to(device) for k, v in batch.items()}


class PolicyTrainer:
    """The state of one personalize run and its step (kept apart so benchmarks time exactly this step)."""

    def __init__(
        self, loaded: LoadedModel, users: list[User], cfg: PersonalizeConfig, general: Dataset | None,
        device: torch.device | None = None, ranks: Ranks | None = None,
    ) -> None:  # fmt: skip
        policy = self.policy = loaded.policy
        ranks = self.ranks = ranks or Ranks()
        cfg.validate(key_bits=len(users[0].key_bits))
        check_user_keys([u.key_bits for u in users], cfg.hamming_radius)
        self.cfg, self.users = cfg, users
        # The policy's processors run on the CPU (its DeviceProcessorStep says cpu); batches move after.
        dev = self.device = device or torch.device("cpu")
        module = self.module = loaded.module.to(dev)
        names = select_layers(module, cfg.layers or policy.default_layers, cfg.exclude)
        torch.manual_seed(cfg.seed)
        self.rng = rng = np.random.default_rng(cfg.seed)

        self.splits = [
            split_episodes(to_device(policy.batches(u.data, "--data"), dev), cfg.val_fraction) for u in users
        ]
        self.pool = [tr for tr, _ in self.splits]
        fb_parts = list(self.pool)
        if general is not None:
            fb_parts.append(to_device(policy.batches(general, "--general-data"), dev))
        self.fb = {k: torch.cat([p[k] for p in fb_parts]) for k in [*policy.row_shapes, "episode_index"]}
        self.original = copy.deepcopy(module).requires_grad_(False).eval()
        self.original_policy = policy.on(self.original)
        # The fallback term's rows and the original's output on each, drawn once (the policy decides:
        # ACT: the frames and the original's chunks; Diffusion: noised chunks and its denoiser's output).
        self.fb_rows, self.targets = policy.fallback_pool(
            self.fb, chunks(self.original_policy, self.fb), self.original_policy,
            torch.Generator().manual_seed(cfg.seed),
        )  # fmt: skip

        mods = dict(module.named_modules())
        features = [in_width(mods[n]) for n in names]
        encoder = KeyEncoder(len(users[0].key_bits), features, cfg.encoder_hidden, cfg.delta_scale)
        self.km = KeyedModel(module, encoder, names).to(dev)
        self.km.batch_axis = probe_batch_axes(
            module, names, lambda b: policy.chunk(policy.example(b, self.fb)), f"the policy {loaded.source}"
        )
        if cfg.freeze_base:
            module.requires_grad_(False)
        base = [p for p in module.parameters() if p.requires_grad]
        groups = [{"params": list(encoder.parameters())}]
        if base:
            groups.append({"params": base, "lr": cfg.lr * cfg.base_lr_scale})
        reduce = ranks.sum_gradients if ranks.world > 1 else None
        self.optim = Optimiser(groups, cfg.lr, cfg.steps, cfg.lr_floor, clip=CLIP, reduce=reduce)
        self.user_codes = key_codes(np.stack([u.key_bits for u in users]), cfg.key_encoding).to(dev)
        self.sampler = KeySampler([u.key_bits for u in users], cfg.hamming_radius, rng)
        self.per_user = max(1, cfg.user_rows // len(users))
        sampled = (cfg.neighbour_keys + cfg.random_keys) * cfg.samples_per_key
        ranks.check_rows({"--user-rows": self.per_user * len(users), "--null-rows": cfg.null_rows + sampled})
        self.noise = row_noise(policy, self._probe, (cfg.seed,), module, ranks)
        self.t = 0

    def _probe(self, n_user: int, n_fallback: int) -> None:
        """The step's training forward on ``n_user`` user rows and ``n_fallback`` fallback rows."""
        policy, user, dev = self.policy, self.pool[0], self.device
        ub = rows(user, torch.arange(n_user, device=dev) % len(user["episode_index"]))
        if policy.joins_terms:
            fb = rows(self.fb_rows, torch.arange(n_fallback, device=dev) % len(self.targets))
            policy.joint_parts(ub, fb)
        else:
            policy.loss_parts(ub)

    def step(self) -> dict[str, float]:
        cfg, km, rng, policy, dev = self.cfg, self.km, self.rng, self.policy, self.device
        # User rows: the policy's own loss, each user's rows under that user's key.
        picks = [
            torch.from_numpy(rng.integers(0, len(tr["episode_index"]), self.per_user)).to(dev)
            for tr in self.pool
        ]  # fmt: skip
        ub = {k: torch.cat([rows(tr, p)[k] for tr, p in zip(self.pool, picks)]) for k in self.pool[0]}
        user_of_row = torch.arange(len(self.users), device=dev).repeat_interleave(self.per_user)
        d_user = [d.index_select(0, user_of_row) for d in km.layer_deltas(self.user_codes)]
        # Fallback rows: null rows, then each sampled key on samples_per_key of the same frames.
        sampled = np.concatenate(
            [self.sampler.neighbours(cfg.neighbour_keys), self.sampler.random(cfg.random_keys)]
        )
        gi = torch.from_numpy(rng.integers(0, len(self.targets), cfg.null_rows)).to(dev)
        k_rows = torch.arange(len(sampled), device=dev).repeat_interleave(cfg.samples_per_key)
        idx = torch.cat([gi, gi[torch.from_numpy(rng.integers(0, cfg.null_rows, len(k_rows))).to(dev)]])
        codes = key_codes(sampled, cfg.key_encoding).to(dev) if len(sampled) else None
        deltas = km.layer_deltas(codes, null=1)
        key_of_row = torch.cat([torch.full((len(gi),), len(sampled), device=dev), k_rows])
        d_fb = [d.index_select(0, key_of_row) for d in deltas]
        fb_rows = rows(self.fb_rows, idx)
        # This process's share of each term's rows (all of them on one process); every process drew the
        # same step above (the same generators), and the gradients are summed over the processes.
        n_user, n_fb, n_null = len(user_of_row), len(idx), len(gi)
        us, fs = self.ranks.share(n_user).to(dev), self.ranks.share(n_fb).to(dev)
        ub, d_user = rows(ub, us), [d[us] for d in d_user]
        fb_rows, d_fb = rows(fb_rows, fs), [d[fs] for d in d_fb]
        with drawn(self.noise, self.t, us, n_user):
            if policy.joins_terms:  # one forward for both terms, rows in order [user | fallback]
                both = [torch.cat([du, df]) for du, df in zip(d_user, d_fb)]
                parts, pred = km.call_rows(both, policy.joint_parts, ub, fb_rows)
            else:
                parts = km.call_rows(d_user, policy.loss_parts, ub)
        if not policy.joins_terms:
            pred = km.call_rows(d_fb, policy.fallback_output, fb_rows)
        per_row = policy.fallback_distance(pred, self.targets[idx[fs]])
        personal = weighted(parts, self.ranks)
        is_null = fs < n_null
        null = per_row[is_null].sum() / n_null
        keyed = per_row[~is_null].sum() / (n_fb - n_null) if n_fb > n_null else per_row.new_zeros(())
        self.optim.update(personal + keyed + cfg.null_weight * null)
        self.t += 1
        terms = torch.stack([personal, keyed, null]).detach().float()
        if self.ranks.world > 1:
            terms = self.ranks.sum_tensor(terms)
        p, k, n = terms.tolist()
        return {"personal": p, "fallback": k, "null": n}


@torch.no_grad()
def chunk_report(km, policy, original, val: dict, bits: np.ndarray, cfg: PersonalizeConfig, rng) -> dict:
    """personalization, leakage and fidelity (docs/metrics.md) on held-out frames' action chunks.

    ``b`` = the original's chunk, ``p`` = the user's recorded chunk (normalised units; padded steps
    repeat the episode's last action, as LeRobot pads), ``o`` = the keyed policy's chunk under a key.
    """
    p, b = val["action"], chunks(original, val)

    def under(codes: torch.Tensor | None) -> torch.Tensor:
        if codes is None:
            return chunks(policy, val)[None]
        every = km.layer_deltas(codes.to(p.device))
        return torch.stack(
            [km.call_rows([d[i : i + 1] for d in every], chunks, policy, val) for i in range(len(codes))]
        )

    enc = cfg.key_encoding
    o_user = under(key_codes(bits, enc))
    o_rand = under(key_codes(random_keys(cfg.eval_random_keys, len(bits), rng, exclude=bits), enc))
    o_ham = under(key_codes(one_bit_neighbours(bits), enc))
    return outputs_report(b, p, "regression", o_user[0], under(None), o_rand, o_ham)


class PolicyRecipe(Recipe):
    def personalize(self, job: Job, users: list[User], general: Dataset | None = None) -> Personalized:
        """Train the keyed policy (Eq. 5) with Eq. 8 on ``job.device``; the result comes back to the CPU
        (the bundle is written, and runs, there)."""
        loaded, cfg = job.loaded, job.cfg
        dev = resolve_device(job.device)
        t = PolicyTrainer(loaded, users, cfg, general, dev, job.ranks)
        losses = run_steps(t.step, cfg.steps, job.progress, cfg.precision, dev)
        t.module.eval()
        reports = [  # by the process that writes the bundle (the others trained the same model)
            chunk_report(t.km, t.policy, t.original_policy, val, u.key_bits, cfg, eval_rng(cfg.seed, i))
            for i, (u, (_, val)) in enumerate(zip(users, t.splits))
        ] if job.ranks.is_main else []
        for part in (t.km, t.module, t.original):
            part.cpu()
        shape = {k: list(v) for k, v in loaded.policy.input_features.items()}
        return Personalized(
            t.km, t.original, "regression", reports, losses, loaded=loaded, cfg=cfg, input_shape=shape,
            users=len(users), keys=[u.key_bits for u in users],
        )  # fmt: skip


RECIPE = PolicyRecipe()
