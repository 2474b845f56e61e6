"""T3 few-shot: an attacker with k labelled samples of the user's behaviour (k = 1, 4, 16, 64).

On the bundle, two fits to the k samples: the encoder's input code (relaxed through the encoder,
then rounded to ±1) and each keyed layer's delta directly (within the encoder's range). Everything is
scored on the audit samples, which the fits never see. Two rows per k:

- ``fewshot k=K``: the relaxed code and the delta (a search row, bounded leakage); its control is what
  the same k samples give without the bundle: the delta fit on the original checkpoint, and plain
  fine-tuning of the original's keyed layers;
- ``fewshot k=K rounded``: the rounded code, a concrete code anyone holding the files can run (a key
  row); its control is the same code where no user was enrolled.

The k samples are rows of ``--data`` outside the audit sample. The code fit's budget
(``--fewshot-restarts`` x ``--fewshot-steps``) comes from the hit-rate study in docs/audit.md
(``benchmarks/bench_fewshot_hits.py``).
"""

from __future__ import annotations

import copy
import zlib

import torch
import torch.nn.functional as F

from .base import (
    NOT_STEPPED,
    Group,
    Probe,
    ProbeContext,
    Reference,
    backward_rows,
    codes_unenrolled,
    model_key,
    moves,
)

SHOTS = (1, 4, 16, 64)
RESTARTS, STEPS, LR = 8, 100, 0.1  # the delta fit's budget (its control runs the same)
FINETUNE_LR = 1e-3


def _loss(o: torch.Tensor, y: torch.Tensor, task: str) -> torch.Tensor:
    """Per key: the attacker's fit to its k samples (cross-entropy or mse)."""
    if task == "classification":
        k = o.shape[0]
        return F.cross_entropy(o.flatten(0, 1), y.repeat(k), reduction="none").view(k, -1).mean(1)
    return ((o - y[None]) ** 2).flatten(1).mean(1)


def _fit(
    params: list[torch.Tensor], backward, steps: int = STEPS, lr: float = LR, ctx: ProbeContext | None = None,
    stage: str = "fewshot", rows: int = 1,
) -> None:  # fmt: skip
    """Adam on ``params``, ``backward()`` putting each step's gradient of the summed loss on them (restarts
    are independent: each one's gradient is its own); stops where a step of ``rows`` rows would outlast
    ``ctx``'s budget (``stage`` is then cut short)."""
    opt = torch.optim.Adam(params, lr=lr)
    for _ in range(steps):
        if ctx is not None and not ctx.affordable(rows, stage):  # the budget: the steps done so far
            break
        opt.zero_grad(set_to_none=True)
        backward()
        opt.step()


def _backward(ctx: ProbeContext, shots: Reference, deltas) -> None:
    """The fit's step: each key's loss on the shots, backward within ``backward_rows``' memory bound."""
    backward_rows(ctx, shots.x, shots.p, deltas(), lambda o, y: _loss(o, y, shots.task))


def fit_codes(
    ctx: ProbeContext, shots: Reference, gen: torch.Generator, restarts: int, steps: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Every restart's relaxed code fitted to the shots, and its final fit loss (the attacker's criterion:
    it knows only its k samples)."""
    km = ctx.km
    u = torch.rand(restarts, km.encoder.code_bits, generator=gen).clamp(0.02, 0.98)
    theta = torch.logit(u).to(shots.x.device).requires_grad_(True)

    def deltas() -> list[torch.Tensor]:
        return km.layer_deltas(torch.tanh(theta / 2))

    def loss() -> torch.Tensor:
        return _loss(km.run_keys(shots.x, deltas()), shots.p, shots.task)

    if moves([theta], deltas()):  # else every gradient is 0: nothing moves
        stage, rows = f"fewshot k={len(shots.x)}", restarts * len(shots.x)
        _fit([theta], lambda: _backward(ctx, shots, deltas), steps, ctx=ctx, stage=stage, rows=rows)
    else:
        ctx.shortcut(NOT_STEPPED)
    with torch.no_grad():
        return torch.tanh(theta / 2), loss()


def _fit_code(ctx: ProbeContext, shots: Reference, gen: torch.Generator) -> torch.Tensor:
    s = ctx.settings
    codes, losses = fit_codes(ctx, shots, gen, s.fewshot_restarts, s.fewshot_steps)
    return codes[int(torch.argmin(losses))][None]


SHARED = "same model as control: the delta fit measured once, for this row and its control"


def _fit_delta(ctx: ProbeContext, shots: Reference, gen: torch.Generator) -> list[torch.Tensor]:
    """The delta fit, or its result where the attacked model is its control's (a sealed bundle's base,
    ``ProbeContext.shared_searches``) and the same fit already ran: the row and its control are then one
    computation (``latent._same_search``'s model key, the same shots and generator state)."""
    if not ctx.shared_searches:
        return _fit_delta_run(ctx, shots, gen)
    key = ("fewshot delta", model_key(ctx.km), id(ctx.shots.x), len(shots.x), ctx.probe,
           zlib.crc32(gen.get_state().numpy().tobytes()))  # fmt: skip
    ctx.shortcut(SHARED)
    done = ctx.kept.get(key)
    if done is None:
        fitted = _fit_delta_run(ctx, shots, gen)
        done = ctx.kept[key] = (fitted, ctx.km.module, ctx.shots.x)  # held: their ids stay theirs
    return done[0]


def _fit_delta_run(ctx: ProbeContext, shots: Reference, gen: torch.Generator) -> list[torch.Tensor]:
    km, scale = ctx.km, ctx.km.encoder.scale
    phis = []
    for f in km.encoder.features:
        p = torch.randn(RESTARTS, f, generator=gen) * 0.5
        p[0] = 0  # one restart from delta = 1: the base itself
        phis.append(p.to(shots.x.device).requires_grad_(True))

    def deltas() -> list[torch.Tensor]:
        return [1.0 + scale * torch.tanh(p) for p in phis]

    def loss() -> torch.Tensor:
        return _loss(km.run_keys(shots.x, deltas()), shots.p, shots.task)

    _fit(phis, lambda: _backward(ctx, shots, deltas), ctx=ctx, stage=f"fewshot k={len(shots.x)}",
         rows=RESTARTS * len(shots.x))  # fmt: skip
    with torch.no_grad():
        i = int(torch.argmin(loss()))
        return [d[i : i + 1].detach() for d in deltas()]


def _score_deltas(ctx: ProbeContext, deltas: list[torch.Tensor], stage: str) -> dict[str, torch.Tensor]:
    """``probe_deltas``, scored once where the row and its control are one computation (the same fitted
    deltas on the same model: ``ProbeContext.shared_searches``)."""
    if not ctx.shared_searches:
        return ctx.probe_deltas(deltas, stage)
    key = ("fewshot scores", model_key(ctx.km), id(deltas[0]), id(ctx.ref.x))
    done = ctx.kept.get(key)
    if done is None:
        done = ctx.kept[key] = (ctx.probe_deltas(deltas, stage), ctx.km.module, deltas, ctx.ref.x)
    return done[0]


def _finetune(ctx: ProbeContext, shots: Reference) -> dict[str, torch.Tensor]:
    """Plain fine-tuning of the keyed layers' weights of the model (no key involved)."""
    own = dict(ctx.km.module.named_modules())
    tuned = {id(p) for n in ctx.km.layer_names for p in own[n].parameters()}
    # The copy's hooks stay idle (no key rows are ever set); only the keyed layers' weights are its own.
    shared = {id(t): t for t in (*ctx.km.module.parameters(), *ctx.km.module.buffers()) if id(t) not in tuned}
    module = copy.deepcopy(ctx.km.module, shared)
    mods = dict(module.named_modules())
    params = [p for n in ctx.km.layer_names for p in mods[n].parameters()]
    module.requires_grad_(False)  # the shared ones too: the audit holds every weight frozen anyway
    for p in params:
        p.requires_grad_(True)

    def backward() -> None:
        _loss(module(shots.x)[None], shots.p, shots.task).sum().backward()

    _fit(params, backward, lr=FINETUNE_LR, ctx=ctx,
         stage=f"fewshot k={len(shots.x)} fine-tune", rows=len(shots.x))  # fmt: skip
    with torch.inference_mode():
        x, step = ctx.ref.x, ctx.km.max_rows or len(ctx.ref.x)
        return ctx.scores(torch.cat([module(x[i : i + step]) for i in range(0, len(x), step)])[None])


def shots_of(ctx: ProbeContext, k: int) -> Reference:
    s = ctx.shots
    return Reference(s.x[:k], s.b[:k], s.p[:k], s.task)


def _ks(ctx: ProbeContext) -> list[int]:
    n = 0 if ctx.shots is None else len(ctx.shots.x)
    return [k for k in SHOTS if k <= n]


def _group(k: int, parts: list[dict[str, torch.Tensor]], what: list[str]) -> Group:
    values = {m: torch.cat([p[m].detach().cpu() for p in parts]) for m in parts[0]}
    return Group(f"fewshot k={k}", values, is_key=False, search={"shots": k, "candidates": what})


def run(ctx: ProbeContext) -> list[Group]:
    groups = []
    for k in _ks(ctx):
        shots = shots_of(ctx, k)
        code = _fit_code(ctx, shots, ctx.generator())
        rounded = torch.where(code >= 0, 1.0, -1.0)
        parts = [ctx.probe_codes(code, f"fewshot k={k}"),
                 _score_deltas(ctx, _fit_delta(ctx, shots, ctx.generator()), f"fewshot k={k}")]  # fmt: skip
        groups.append(_group(k, parts, ["code (relaxed)", "delta"]))
        key = _group(k, [ctx.probe_codes(rounded, f"fewshot k={k}")], ["code (rounded)"])
        key.name, key.codes, key.kind = f"fewshot k={k} rounded", rounded, "key"
        if ctx.has_key:  # 0 = the fit found the user's own code
            key.search["code_distance"] = int((rounded != ctx.codes(ctx.keys[0])).sum())
        groups.append(key)
    return groups


def control(ctx: ProbeContext, found: list[Group]) -> list[Group]:
    groups = codes_unenrolled(ctx, [g for g in found if g.kind == "key"])
    if ctx.original is None:
        return groups
    orig = ctx.on(ctx.original)
    for k in _ks(ctx):
        shots = shots_of(ctx, k)
        fitted = _fit_delta(orig, shots, ctx.generator())
        parts = [_score_deltas(orig, fitted, f"fewshot k={k} control"), _finetune(orig, shots)]
        groups.append(_group(k, parts, ["delta", "fine-tune keyed layers"]))
    return groups


PROBE = Probe(
    "fewshot", "T3", "search",
    "the code and the delta fitted to k = 1..64 of your samples; control: the same on the original",
    run, control=control, needs="key", known=lambda ctx: not _ks(ctx),  # no rows outside the sample: no fit
)  # fmt: skip
