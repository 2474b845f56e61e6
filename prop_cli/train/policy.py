"""Recipe: a policy that brings its own loss (a LeRobot policy), unsealed: Eq. 8 with the policy's
own terms, which the policy protocol (``PolicyProtocol``) supplies.

User term: the policy's own training loss (ACT: L1 on the action chunk, padding masked, plus its
VAE's KL; Diffusion: its noise-prediction MSE) on the user's frames, every row under the user's key.
Fallback terms (the null key, weighted by ``null_weight``; K1 Hamming neighbours and K2 random keys)
distil the frozen original on general observations ("distill"): ACT's deployed chunk, L1; Diffusion's
and SmolVLA's denoiser on the same (observation, x_t, t) rows, MSE. Each target is computed once, when
a step first draws its row, and kept (``FallbackPool``). Measured against the policy's loss on general
data and against relabelled actions, the distilled fallback kept wrong keys at the base's closed-loop
success and the no-key chunk closest to the original's (examples/RESULTS.md, "LeRobot ACT").

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
import time
from collections.abc import Callable

import numpy as np
import torch

from prop_adapters import LoadedModel
from prop_adapters.base import FRAME
from prop_cli.config import TrainConfig, UnsealedConfig
from prop_cli.core.batch_axes import probe_batch_axes
from prop_cli.core.device import resolve_device
from prop_cli.core.key_sampling import HARD_STREAM, KeySampler, one_bit_neighbours, random_keys
from prop_cli.core.keyed_model import KeyedModel, KeyEncoder, key_codes
from prop_cli.core.layers import in_width, select_layers
from prop_cli.datasources import Dataset
from prop_cli.errors import PropError

from .distributed import Ranks
from .frozen import frozen_in_bf16, held_autocast, trained_in_fp32
from .hardening import antipode_codes, far_codes
from .loop import Optimiser, mixed_precision, run_steps
from .objective import check_user_keys, delta_pull
from .recipe import Job, Recipe, User
from .report import eval_rng, outputs_report
from .row_noise import RowNoise
from .unsealed import Personalized

_CHUNK = 256  # rows per forward when caching the original's chunks
HARD_FRAMES = 8  # fallback rows each hard-negative candidate key is scored on (KeySampler.step)
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
def chunks(policy, batch: dict[str, torch.Tensor], per_forward: int = _CHUNK) -> torch.Tensor:
    """The policy's deployed chunk for every frame of ``batch``, ``per_forward`` frames per forward."""
    n = len(batch["episode_index"])
    idx = torch.arange(n, device=batch["episode_index"].device)
    return torch.cat([policy.chunk(rows(batch, idx[i : i + per_forward])) for i in range(0, n, per_forward)])


def forward_rows(step_rows: int) -> int:
    """Rows per forward outside the step (the original's chunks and targets, the report): no more than a
    step holds with its gradients, so their memory stays within the step's at any data size."""
    return max(1, min(_CHUNK, step_rows))


class FallbackPool:
    """The fallback term's rows and the original's output on each (the policy's ``fallback_pool``),
    computed when a step first draws them and kept: nothing runs before the first step, a short run
    computes only the rows it uses and a long one each row once, as a pool drawn up front would. Each
    forward holds at most ``per_forward`` rows and a row refers to its frame instead of copying it, so
    memory does not grow with the rows drawn at once. The random draws (``fallback_noise``) are made
    up front, in the order a pool drawn whole makes them. Targets are computed in fp32 (outside the
    step's autocast), as they were before the steps; under the step's autocast where the original's
    frozen weights are held bf16 (``frozen_in_bf16``)."""

    def __init__(
        self, policy, original, frames: dict[str, torch.Tensor], generator: torch.Generator, per_forward: int,
        module: torch.nn.Module | None = None,
    ) -> None:  # fmt: skip
        """``module``: the original's module (whose weights may be held bf16)."""
        self.policy, self.original, self.frames, self.per = policy, original, frames, per_forward
        self.module = module
        n = len(frames["episode_index"])
        noise = policy.fallback_noise(n, generator)
        self.whole = None
        if noise is NotImplemented:  # a policy's own pool without a lazy form: drawn whole, now
            drawn = chunks(original, frames, per_forward)
            self.whole = policy.fallback_pool(frames, drawn, original, generator)
            self.size = len(self.whole[1])
            return
        dev = frames["episode_index"].device
        self.noise = None if noise is None else {k: v.to(dev) for k, v in noise.items() if k != FRAME}
        self.frame = (torch.arange(n) if noise is None else noise[FRAME]).to(dev)
        self.size = len(self.frame)
        self._chunks: torch.Tensor | None = None  # the original's chunk per frame, once computed
        self._targets: torch.Tensor | None = None  # the original's output per row, once computed
        self._have_chunk = torch.zeros(n, dtype=torch.bool, device=dev)
        self._have_target = torch.zeros(self.size, dtype=torch.bool, device=dev)
        # --fallback-times trajectory: a row's x_t is the original's own sampler state at its step, kept
        self.follows = policy.fallback_times == "trajectory" and self.noise is not None
        self._states: torch.Tensor | None = None
        self._have_state = torch.zeros(self.size if self.follows else 0, dtype=torch.bool, device=dev)

    def __len__(self) -> int:
        return self.size

    @torch.no_grad()
    def take(self, idx: torch.Tensor) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        """Rows ``idx`` of the pool and their targets."""
        if self.whole is not None:
            pool, targets = self.whole
            return rows(pool, idx), targets[idx]
        # fp32 unless the original's frozen weights are held bf16 (--precision bf16, ``frozen_in_bf16``):
        # then under the step's autocast, the arithmetic its matrices take anyway.
        held = self.module is not None and any(p.dtype == torch.bfloat16 for p in self.module.parameters())
        with contextlib.nullcontext() if held else torch.autocast(idx.device.type, enabled=False):
            frames = self.frame[idx]
            if self.follows:  # the rows' sampler states, not their frames' clean chunks
                self._states = self._fill(self._states, self._have_state, idx, self._row_states)
            else:
                self._chunks = self._fill(self._chunks, self._have_chunk, frames, self._frame_chunks)
            if self.noise is None:  # deterministic: the rows are the frames, the targets their chunks
                return rows(self.frames, frames), self._chunks[frames]
            self._targets = self._fill(self._targets, self._have_target, idx, self._row_targets)
            return self._rows(idx), self._targets[idx]

    def _fill(self, store, have: torch.Tensor, idx: torch.Tensor, compute):
        todo = idx.unique()
        todo = todo[~have[todo]]
        for i in range(0, len(todo), self.per):
            part = todo[i : i + self.per]
            out = compute(part).float()
            if store is None:
                store = out.new_empty((len(have), *out.shape[1:]))
            store[part] = out
            have[part] = True
        return store

    def _frame_chunks(self, frames: torch.Tensor) -> torch.Tensor:
        return self.original.chunk(rows(self.frames, frames))

    def _row_targets(self, idx: torch.Tensor) -> torch.Tensor:
        return self.original.fallback_output(self._rows(idx))

    def _row_states(self, idx: torch.Tensor) -> torch.Tensor:
        noise = {k: v[idx] for k, v in self.noise.items()}
        return self.original.fallback_states(rows(self.frames, self.frame[idx]), noise)

    def _rows(self, idx: torch.Tensor) -> dict[str, torch.Tensor]:
        frames = self.frame[idx]
        noise = {k: v[idx] for k, v in self.noise.items()}
        x = self._states[idx] if self.follows else self._chunks[frames]
        return rows(self.frames, frames) | self.policy.fallback_inputs(x, noise)


def frozen_twin(module: torch.nn.Module) -> torch.nn.Module:
    """The frozen original beside ``module``: a copy that shares every parameter that does not train
    (the policy's own frozen parts, e.g. SmolVLA's VLM; all of them under --freeze-base) and copies only
    those that do. One copy of the base in memory, not two (SmolVLA at its published size: 0.4 GB for
    the original's trainable 100 M parameters instead of 1.8 GB)."""
    shared = {id(p): p for p in module.parameters() if not p.requires_grad}
    return copy.deepcopy(module, shared).requires_grad_(False).eval()


def row_noise(
    policy, forward, seed: tuple[int, ...], module: torch.nn.Module, ranks: Ranks,
    amp: contextlib.AbstractContextManager | None = None,
) -> RowNoise | None:  # fmt: skip
    """The per-row draws of the policy's training forward (``row_noise``); None where it draws
    nothing. A policy whose draws cannot be made per row trains on one process only. ``amp``: the
    steps' autocast (``loop.mixed_precision``), which the probe's forward runs in as theirs do (weights
    held bf16 take fp32 inputs only under it)."""
    with amp or contextlib.nullcontext():
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
        self, loaded: LoadedModel, users: list[User], tc: TrainConfig, cfg: UnsealedConfig,
        general: Dataset | None, device: torch.device | None = None, ranks: Ranks | None = None,
    ) -> None:  # fmt: skip
        policy = self.policy = loaded.policy
        ranks = self.ranks = ranks or Ranks()
        cfg = cfg.for_kind("policy")  # --delta-pull's policy default where none was given
        cfg.check_key_bits(len(users[0].key_bits))
        check_user_keys([u.key_bits for u in users], cfg.hamming_radius)
        self.tc, self.cfg, self.users = tc, cfg, users
        # The policy's processors run on the CPU (its DeviceProcessorStep says cpu); batches move after.
        dev = self.device = device or torch.device("cpu")
        module = self.module = loaded.module.to(dev)
        names = select_layers(module, tc.layers or policy.default_layers, tc.exclude)
        torch.manual_seed(tc.seed)
        self.rng = rng = np.random.default_rng(tc.seed)

        self.splits = [
            split_episodes(to_device(policy.batches(u.data, "--data"), dev), tc.val_fraction) for u in users
        ]
        self.pool = [tr for tr, _ in self.splits]
        fb_parts = list(self.pool)
        if general is not None:
            fb_parts.append(to_device(policy.batches(general, "--general-data"), dev))
        keys = [*policy.row_shapes, "episode_index"]
        one = len(fb_parts) == 1  # the users' frames alone: no copy
        self.fb = {k: fb_parts[0][k] if one else torch.cat([p[k] for p in fb_parts]) for k in keys}
        if cfg.freeze_base:
            module.requires_grad_(False)
        self.original = frozen_twin(module)
        trained_in_fp32(module)  # after the twin: the original's copy stays as the checkpoint holds it
        self.original_policy = policy.on(self.original)
        # The fallback term's rows and the original's output on each, computed as steps draw them (the
        # policy decides: ACT: the frames and the original's chunks; Diffusion, SmolVLA: noised chunks
        # and the original's denoiser output).
        self.per_forward = forward_rows(cfg.batch_rows(tc.user_rows))
        if cfg.fallback_times == "trajectory" and not getattr(policy, "follows_sampler", False):
            raise PropError(
                f"--fallback-times trajectory: the policy {loaded.source} has no sampler prop can follow "
                "(LeRobot Diffusion only)",
                "use --fallback-times uniform or sampler",
            )
        policy.fallback_times = cfg.fallback_times  # a denoising policy's fallback timesteps
        self.fallback = FallbackPool(
            policy, self.original_policy, self.fb, torch.Generator().manual_seed(tc.seed), self.per_forward,
            self.original,
        )  # fmt: skip

        mods = dict(module.named_modules())
        features = [in_width(mods[n]) for n in names]
        encoder = KeyEncoder(len(users[0].key_bits), features, cfg.encoder_hidden, cfg.delta_scale)
        self.km = KeyedModel(module, encoder, names).to(dev)
        self.km.batch_axis = probe_batch_axes(
            module, names, lambda b: policy.chunk(policy.example(b, self.fb)), f"the policy {loaded.source}"
        )
        # What the policy trains by default (SmolVLA: the action expert and its projections; LeRobot's
        # own freezing, kept as loaded) is what trains here, unless --freeze-base froze it all.
        base = [p for p in module.parameters() if p.requires_grad]
        groups = [{"params": list(encoder.parameters())}]
        if base:
            groups.append({"params": base, "lr": cfg.lr * cfg.base_lr_scale})
        reduce = ranks.sum_gradients if ranks.world > 1 else None
        self.optim = Optimiser(groups, cfg.lr, tc.steps, tc.lr_floor, clip=CLIP, reduce=reduce)
        self.user_codes = key_codes(np.stack([u.key_bits for u in users]), cfg.key_encoding).to(dev)
        # After the probe: from here to ``finish`` the frozen weights may be bf16 (shared with the original).
        self.restore = frozen_in_bf16(module, loaded) if tc.precision == "bf16" else None
        self.sampler = KeySampler(
            [u.key_bits for u in users], cfg.hamming_radius, rng,
            cfg.hard_negatives, cfg.hard_pool, cfg.hard_every,
        )  # fmt: skip
        self.hard_rng = np.random.default_rng((tc.seed, HARD_STREAM))
        self.per_user = max(1, tc.user_rows // len(users))
        n_placed = cfg.far_codes + cfg.hardening.antipode_codes
        sampled = (cfg.neighbour_keys + cfg.random_keys + n_placed) * cfg.samples_per_key
        ranks.check_rows({"--user-rows": self.per_user * len(users), "--null-rows": cfg.null_rows + sampled})
        amp = mixed_precision(tc.precision, dev)
        self.noise = row_noise(policy, self._probe, (tc.seed,), module, ranks, amp)
        self.t = 0
        self.last_fallback: dict[str, float] = {}  # the fallback terms of the last step that ran them

    def _probe(self, n_user: int, n_fallback: int) -> None:
        """The step's training forward on ``n_user`` user rows and ``n_fallback`` fallback rows."""
        policy, user, dev = self.policy, self.pool[0], self.device
        ub = rows(user, torch.arange(n_user, device=dev) % len(user["episode_index"]))
        if policy.joins_terms:
            fb, _ = self.fallback.take(torch.arange(n_fallback, device=dev) % len(self.fallback))
            policy.joint_parts(ub, fb)
        else:
            policy.loss_parts(ub)

    @torch.no_grad()
    def divergence(self, keys: np.ndarray) -> np.ndarray:
        """The hard-negative score (``KeySampler.step``): each key's fallback distance, Eq. 8's own term,
        on ``HARD_FRAMES`` fallback rows drawn afresh per scoring (a stream of its own)."""
        idx = torch.from_numpy(self.hard_rng.integers(0, len(self.fallback), HARD_FRAMES)).to(self.device)
        fb_rows, targets = self.fallback.take(idx)
        deltas = self.km.layer_deltas(key_codes(keys, self.cfg.key_encoding).to(self.device))
        pred = pair_outputs(self.km, self.policy.fallback_output, fb_rows, deltas, self.per_forward)
        row_of = torch.arange(len(idx), device=self.device).repeat(len(keys))
        dist = self.policy.fallback_distance(pred, targets[row_of]).float()
        return dist.reshape(len(keys), len(idx)).mean(1).cpu().numpy()

    def finish(self) -> None:
        """After the last step: the optimiser's state and the gradients freed, the frozen weights back as
        the checkpoint holds them (``frozen_in_bf16``), the module in eval mode: what the report runs."""
        self.optim = None
        for p in (*self.module.parameters(), *self.km.encoder.parameters()):
            p.grad = None
        if self.restore is not None:
            self.restore()
            self.restore = None
        self.module.eval()

    def step(self) -> dict[str, float]:
        cfg, km, rng, policy, dev = self.cfg, self.km, self.rng, self.policy, self.device
        # The last update's gradients freed before this forward builds its activations, as LeRobot's loop
        # frees them (SmolVLA at its published size: 0.4 GB for the 100 M trained parameters).
        self.optim.adam.zero_grad()
        self.sampler.step(self.divergence)  # every hard_every steps: the hard negatives re-chosen
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
        # The sampled keys, then --antipode-codes (72-88 bits from the user's code: pulled, as K1 and K2),
        # then the far codes (40-56 bits: not pulled); one slice for the pull, as in the array trainer.
        n_anti = cfg.hardening.antipode_codes
        n_keys = len(sampled) + n_anti + cfg.far_codes
        gi = torch.from_numpy(rng.integers(0, len(self.fallback), cfg.null_rows)).to(dev)
        k_rows = torch.arange(n_keys, device=dev).repeat_interleave(cfg.samples_per_key)
        idx = torch.cat([gi, gi[torch.from_numpy(rng.integers(0, cfg.null_rows, len(k_rows))).to(dev)]])
        parts = [key_codes(sampled, cfg.key_encoding).to(dev)] if len(sampled) else []
        if n_anti:
            parts.append(antipode_codes(self.user_codes, n_anti, rng))
        if cfg.far_codes:
            parts.append(far_codes(self.user_codes, cfg.far_codes, rng))
        codes = torch.cat(parts) if parts else None
        deltas = km.layer_deltas(codes, null=1)
        if self.t % cfg.fallback_every:  # --fallback-every: the user's rows and the pull alone this step
            return self._user_step(ub, d_user, deltas, len(sampled) + n_anti, n_keys)
        key_of_row = torch.cat([torch.full((len(gi),), n_keys, device=dev), k_rows])
        d_fb = [d.index_select(0, key_of_row) for d in deltas]
        # This process's share of each term's rows (all of them on one process); every process drew the
        # same step above (the same generators), and the gradients are summed over the processes.
        n_user, n_fb, n_null = len(user_of_row), len(idx), len(gi)
        us, fs = self.ranks.share(n_user).to(dev), self.ranks.share(n_fb).to(dev)
        ub, d_user = rows(ub, us), [d[us] for d in d_user]
        # The step's targets for every process's rows (FallbackPool: computed where first drawn), so each
        # is computed in the same batch on any number of processes, then this process's share.
        fb_rows, targets = self.fallback.take(idx)
        fb_rows, targets, d_fb = rows(fb_rows, fs), targets[fs], [d[fs] for d in d_fb]
        with drawn(self.noise, self.t, us, n_user):
            if policy.joins_terms:  # one forward for both terms, rows in order [user | fallback]
                both = [torch.cat([du, df]) for du, df in zip(d_user, d_fb)]
                parts, pred = km.call_rows(both, policy.joint_parts, ub, fb_rows)
            else:
                parts = km.call_rows(d_user, policy.loss_parts, ub)
        if not policy.joins_terms:
            pred = km.call_rows(d_fb, policy.fallback_output, fb_rows)
        per_row = policy.fallback_distance(pred, targets)
        personal = weighted(parts, self.ranks)
        is_null = fs < n_null
        null = per_row[is_null].sum() / n_null
        # K1 and K2's rows, then the antipode and far codes' (train.hardening): a term each, as arrays do.
        is_far = fs >= n_null + len(sampled) * cfg.samples_per_key
        n_far = (n_anti + cfg.far_codes) * cfg.samples_per_key
        n_kk = n_fb - n_null - n_far
        keyed = per_row[~is_null & ~is_far].sum() / n_kk if n_kk else per_row.new_zeros(())
        if n_far:
            keyed = keyed + per_row[is_far].sum() / n_far
        if cfg.fallback_every == 1:
            loss = personal + cfg.key_weight * keyed + cfg.null_weight * null
        else:  # weighted k: over k steps the objective's expectation is Eq. 8's
            loss = personal + cfg.fallback_every * (cfg.key_weight * keyed + cfg.null_weight * null)
        if cfg.delta_pull:  # K1 and K2 (objective.delta_pull); every process's share of the encoder-only term
            pull = delta_pull(deltas, slice(0, len(sampled) + n_anti), of=n_keys)
            loss = loss + cfg.delta_pull * pull / self.ranks.world
        self.optim.update(loss)
        self.t += 1
        terms = torch.stack([personal, keyed, null]).detach().float()
        if self.ranks.world > 1:
            terms = self.ranks.sum_tensor(terms)
        p, k, n = terms.tolist()
        self.last_fallback = {"fallback": k, "null": n}
        return {"personal": p, "fallback": k, "null": n}

    def _user_step(
        self, ub: dict[str, torch.Tensor], d_user: list[torch.Tensor], deltas: list[torch.Tensor],
        n_sampled: int, n_keys: int,
    ) -> dict[str, float]:  # fmt: skip
        """A step between --fallback-every's: the user's rows and the delta pull (the encoder alone), no
        fallback row; the fallback terms reported are the last computed ones."""
        cfg, n_user = self.cfg, len(d_user[0])
        us = self.ranks.share(n_user).to(self.device)
        ub, d_user = rows(ub, us), [d[us] for d in d_user]
        with drawn(self.noise, self.t, us, n_user):
            parts = self.km.call_rows(d_user, self.policy.loss_parts, ub)
        personal = weighted(parts, self.ranks)
        loss = personal
        if cfg.delta_pull:
            pull = delta_pull(deltas, slice(0, n_sampled), of=n_keys)
            loss = loss + cfg.delta_pull * pull / self.ranks.world
        self.optim.update(loss)
        self.t += 1
        p = personal.detach().float()
        if self.ranks.world > 1:
            p = self.ranks.sum_tensor(p)
        return {"personal": float(p), **self.last_fallback}


# The report's default budget in (key condition x held-out frame) chunks: REPORT_WORK / parameters, so a
# small policy's report covers every key on every held-out frame and a large one's stays within about a
# minute of CPU (SmolVLA at its published size, 450 M parameters: 22 chunks of ~135 GFLOP, 1-3 s each on
# 2 cores). --report-budget sets it; 0: no limit.
REPORT_WORK = 1e10
REPORT_MIN_FRAMES = 2  # frames kept before keys are cut


def report_budget(tc: TrainConfig, module: torch.nn.Module) -> int | None:
    """The report's budget in chunks (None: every key condition on every held-out frame)."""
    if tc.report_budget is not None:
        return tc.report_budget or None
    params = sum(p.numel() for p in module.parameters())
    return max(1, int(REPORT_WORK // max(params, 1)))


def report_plan(frames: int, n_random: int, n_ham: int, budget: int | None) -> tuple[int, int, int]:
    """(frames, random keys, 1-bit neighbours) the report runs within ``budget`` chunks, each chunk one
    key condition on one held-out frame; the original, the user's key and no key run on every frame
    kept, and each key group keeps at least one key. Frames go first (down to REPORT_MIN_FRAMES), then
    keys, in equal shares."""
    fixed = 3  # the original, the user's key, no key
    if budget is None or frames * (fixed + n_random + n_ham) <= budget:
        return frames, n_random, n_ham
    f = min(frames, max(REPORT_MIN_FRAMES, budget // (fixed + n_random + n_ham)))
    keys = max(2, budget // f - fixed)
    r = max(1, min(n_random, max(keys // 2, keys - n_ham)))  # what one group leaves, the other takes
    return f, r, max(1, min(n_ham, keys - r))


def time_left(started: float, done: int, total: int) -> str:
    """The estimate of a progress line: the sampler runs left at the speed of those done since
    ``started`` (``time.perf_counter()``)."""
    left = (time.perf_counter() - started) / max(done, 1) * (total - done)
    return f"about {left:.0f} s left" if left >= 1 else "under a second left"


def spaced_frames(val: dict, f: int) -> dict:
    """``f`` of the held-out frames of ``val``, evenly spaced (all of them when ``f`` covers them)."""
    n = len(val["episode_index"])
    if f >= n:
        return val
    return rows(val, torch.from_numpy(np.unique(np.linspace(0, n - 1, f).round().astype(np.int64))))


def pair_outputs(km, fn, data: dict, deltas: list[torch.Tensor], per_forward: int) -> torch.Tensor:
    """``fn`` on every (key, row) pair of K keys (``deltas``: (K, features) per layer) and the rows of
    ``data``, key-major ((K * rows, ...): key 0 on every row, then key 1, ...), ``per_forward`` pairs
    per forward."""
    k, n = deltas[0].shape[0], len(data["episode_index"])
    dev = data["episode_index"].device
    key_of = torch.arange(k, device=dev).repeat_interleave(n)
    row_of = torch.arange(n, device=dev).repeat(k)
    return torch.cat([
        km.call_rows([d.index_select(0, key_of[i : i + per_forward]) for d in deltas], fn,
                     rows(data, row_of[i : i + per_forward]))
        for i in range(0, k * n, per_forward)
    ])  # fmt: skip


def keyed_chunks(km, policy, val: dict, deltas: list[torch.Tensor], per_forward: int) -> torch.Tensor:
    """The chunk of every held-out frame under each of K keys (``deltas``: (K, features) per layer), (K,
    frames, ...): the (key, frame) pairs run through the sampler as rows, ``per_forward`` at a time."""
    out = pair_outputs(km, policy.chunk, val, deltas, per_forward)
    return out.reshape(deltas[0].shape[0], len(val["episode_index"]), *out.shape[1:])


@torch.no_grad()
def chunk_report(
    km, policy, original, val: dict, bits: np.ndarray, cfg: UnsealedConfig, n_random: int, rng,
    budget: int | None = None, per_forward: int = _CHUNK, say: Callable[[str], None] | None = None,
) -> dict:  # fmt: skip
    """personalization, leakage and fidelity (docs/metrics.md) on held-out frames' action chunks.

    ``b`` = the original's chunk, ``p`` = the user's recorded chunk (normalised units; padded steps
    repeat the episode's last action, as LeRobot pads), ``o`` = the keyed policy's chunk under a key.
    Within ``budget`` chunks (``report_plan``): held-out frames evenly spaced, the first random keys and
    a random share of the 1-bit neighbours; ``coverage`` says what ran of what a full report runs.
    """
    enc = cfg.key_encoding
    rand = random_keys(n_random, len(bits), rng, exclude=bits)
    ham = one_bit_neighbours(bits)
    n = len(val["episode_index"])
    f, r, h = report_plan(n, len(rand), len(ham), budget)
    if say is not None:
        say(
            f"{f * (3 + r + h)} sampler runs ({f} held-out frames x {3 + r + h} key conditions; "
            f"--report-budget {budget or 'none'})"
        )
    val = spaced_frames(val, f)
    rand = rand[:r]
    if h < len(ham):
        ham = ham[np.sort(rng.choice(len(ham), h, replace=False))]
    total, done, started = f * (3 + r + h), 0, time.perf_counter()

    def ran(runs: int, what: str) -> None:  # progress: a report of a real-size policy takes minutes
        nonlocal done
        done += runs
        if say is not None and done < total:
            say(f"{done} of {total} sampler runs done ({what}); {time_left(started, done, total)}")

    p, b = val["action"], chunks(original, val, per_forward)
    ran(f, "the original's chunks")

    def under(codes: torch.Tensor | None, what: str) -> torch.Tensor:
        if codes is None:
            out = chunks(policy, val, per_forward)[None]
        else:
            out = keyed_chunks(km, policy, val, km.layer_deltas(codes.to(p.device)), per_forward)
        ran(f * len(out), what)
        return out

    o_user = under(key_codes(bits, enc), "your key's")
    o_null = under(None, "no key's")
    o_rand = under(key_codes(rand, enc), f"{len(rand)} random keys'")
    report = outputs_report(b, p, "regression", o_user[0], o_null, o_rand,
                            under(key_codes(ham, enc), "1-bit neighbours'"))  # fmt: skip
    full = {"frames": n, "random": n_random, "hamming1": len(bits)}
    covered = {"frames": len(p), "random": len(rand), "hamming1": len(ham)}
    if covered != full:
        report["coverage"] = {"ran": covered, "of": full, "budget": budget}
    return report


class PolicyRecipe(Recipe[UnsealedConfig]):
    def personalize(
        self, job: Job[UnsealedConfig], users: list[User], general: Dataset | None = None
    ) -> Personalized:
        """Train the keyed policy (Eq. 5) with Eq. 8 on ``job.device``; the result comes back to the CPU
        (the bundle is written, and runs, there)."""
        loaded, tc, cfg = job.loaded, job.train, job.mode
        dev = resolve_device(job.device)
        # held_autocast: a base held bf16 (keep_dtypes) computes under the steps' autocast throughout.
        with loaded.policy.memo(), held_autocast(loaded.module, dev):  # memo: once for every key (SmolVLA)
            job.say(f"setting up: the users' frames, the fallback samples and keys, per-row noise on {dev}")
            t = PolicyTrainer(loaded, users, tc, cfg, general, dev, job.ranks)
            losses = run_steps(t.step, tc.steps, job.progress, tc.precision, dev)
            t.finish()
            budget = report_budget(tc, t.module)
            reports = [  # by the process that writes the bundle (the others trained the same model)
                chunk_report(t.km, t.policy, t.original_policy, val, u.key_bits, cfg, tc.eval_random_keys,
                             eval_rng(tc.seed, i), budget, t.per_forward,
                             say=lambda what, i=i: job.say(f"report of user {i + 1}: {what}"))
                for i, (u, (_, val)) in enumerate(zip(users, t.splits))
            ] if job.ranks.is_main else []  # fmt: skip
        for part in (t.km, t.module, t.original):
            part.cpu()
        shape = {k: list(v) for k, v in loaded.policy.input_features.items()}
        return Personalized(
            t.km, t.original, "regression", reports, losses, loaded=loaded, cfg=cfg, input_shape=shape,
            users=len(users), keys=[u.key_bits for u in users],
        )  # fmt: skip


RECIPE = PolicyRecipe()
