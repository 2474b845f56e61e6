"""Base drift: does the no-key model's move from the original point at where your data lies?

An unsealed bundle's base weights are trained with the key (``--base-lr-scale`` of the learning rate),
and the fallback keeps the no-key model at the original where it looks: on your data and around it.
What moves the weights is your data, so the move can say where your data is. On the IL example with a
user whose data fills one quadrant of the positions, the first layer's weight change ``dW`` (bundle
base minus original) has its top right singular vector at cos 0.97 with that quadrant's direction, and
the no-key model's outputs moved 29x more outside the quadrant than inside it. ``--freeze-base`` (and a
sealed bundle) keeps the base the original's, bit for bit: nothing moved.

What this probe measures, with the original (``--original``; a sealed or ``--freeze-base`` bundle's
own base otherwise, which prop writes as the original's):

- the layer that reads the inputs (a chain MLP's first ``nn.Linear``; other models are not measured): its
  ``dW``, and ``dW``'s top ``TOP`` right singular vectors, the input directions the drift singles out
  (what anyone holding the bundle and the public original can read, without data);
- for each direction ``v``, how one-sided your samples lie along it: ``2 f - 1``, where ``f`` is the
  share of your samples on the side of the hyperplane ``x . v = 0`` that most of them are on (0: as
  many on each side; 1: all on one), less what chance gives on as many samples (``chance``: 0.12 on
  256), at least 0. Inputs are measured from their origin (standardised features and symmetric state
  spaces are centred there);
- control: the same figure's mean over ``RANDOM_DIRECTIONS`` random directions (the audit's seed): what a
  direction unrelated to your data shows.

The origin is the one reference the audit has: it is not told where the original's inputs lie. Where
they are not centred at the origin (raw pixel values: the digits example), every sample of anyone's
lies along the inputs' mean direction, a base trained on any data moves along it, and the row reads
that offset, not yours: there it flags an unsealed bundle whatever its data (docs/privacy.md).

Rows: one, ``drift``, a row per direction (``keys``: directions); the pick is the top singular vector
(the attacker's read). Its fidelity is the no-key model's against the original on your samples: how far
the outputs moved. Kind "key" (the directions are concrete, gated beyond the control like keys).
"""

from __future__ import annotations

import torch
from torch import nn

from prop_cli.core import metrics

from .base import Group, Probe, ProbeContext
from .screen import chain_ops

TOP = 3  # singular vectors of dW tested
RANDOM_DIRECTIONS = 1024  # the control's directions
CHANCE_Z = 1.96  # the one-sided figure counts beyond what chance gives at 95% (``chance``)


def input_layer(module: nn.Module, width: int) -> tuple[str, nn.Linear] | None:
    """A chain MLP's first layer when it is an ``nn.Linear`` reading all ``width`` input features (other
    models: None; where their inputs meet a first linear layer is not known here)."""
    ops = chain_ops(module)
    if not ops or ops[0][0] != "linear" or ops[0][2].in_features != width:
        return None
    return ops[0][1], ops[0][2]


def one_sided(x: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Per direction (rows of ``dirs``): 2 f - 1, f the share of ``x``'s rows on the side of ``x . v = 0``
    where most of them lie (a row on the hyperplane counts for neither side)."""
    side = torch.sign(x.double() @ dirs.double().T)  # (rows, directions)
    pos, neg = (side > 0).double().mean(0), (side < 0).double().mean(0)
    return (2 * torch.maximum(pos, neg) - 1).clamp_min(0.0).float()


def chance(rows: int) -> float:
    """What ``one_sided`` reaches by chance on ``rows`` samples with no side preferred, at 95%: the
    share on one side is binomial, so 2 f - 1 stays within 1.96 / sqrt(rows)."""
    return CHANCE_Z / rows**0.5


def beyond_chance(x: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(the figure scored: ``one_sided`` less ``chance``, at least 0; ``one_sided`` itself)."""
    raw = one_sided(x, dirs)
    return (raw - chance(len(x))).clamp_min(0.0), raw


def _random_directions(ctx: ProbeContext, width: int) -> torch.Tensor:
    r = torch.randn(RANDOM_DIRECTIONS, width, generator=ctx.generator(), dtype=torch.float64)
    return r / r.norm(dim=1, keepdim=True)


def _measurable(ctx: ProbeContext) -> tuple[torch.Tensor, str, nn.Linear, nn.Linear] | None:
    """(flat inputs, layer name, the bundle's layer, the original's), or None with a note on why not."""
    x = ctx.ref.x.reshape(len(ctx.ref.x), -1)
    found = input_layer(ctx.km.module, x.shape[1])
    if found is None:
        ctx.notes.append(
            "drift: not measured: the model is not a chain MLP whose first linear layer reads the "
            f"{x.shape[1]} input features (a policy's camera and state go through its own layers first)"
        )
        return None
    name, layer = found
    theirs = dict(ctx.original.module.named_modules()).get(name)
    if not isinstance(theirs, nn.Linear) or theirs.weight.shape != layer.weight.shape:
        ctx.notes.append(f"drift: the original has no layer {name} of the bundle's shape: not measured")
        return None
    return x, name, layer, theirs


def _row(ctx: ProbeContext, sided: torch.Tensor, pick: torch.Tensor, moved: torch.Tensor) -> dict:
    """Per direction: leakage (the one-sided figure, with targets), the fidelity of the no-key model to the
    original (the same for every direction) and the divergence the attacker picks by."""
    n = len(sided)
    out = {"fidelity": moved.expand(n).clone(), "divergence": pick}
    if ctx.has_key:
        out["leakage"] = sided
        out["bounded"] = sided
    return out


@torch.no_grad()
def run(ctx: ProbeContext) -> list[Group]:
    got = _measurable(ctx)
    if got is None:
        return []
    x, name, layer, theirs = got
    dw = (layer.weight.detach().double() - theirs.weight.detach().double().to(layer.weight.device)).cpu()
    base, orig = ctx.plain(), ctx.plain(ctx.original)
    moved = metrics.fidelity(base[None], orig, ctx.ref.task)
    info: dict = {"layer": name, "directions": TOP, "weight_change": float(dw.norm())}
    if not bool(dw.any()):  # the base is the original's: no direction to read
        info["singular_values"] = [0.0] * TOP
        sided = torch.zeros(TOP)
        pick = torch.zeros(TOP)
    else:
        _, s, vh = torch.linalg.svd(dw, full_matrices=False)
        dirs = vh[:TOP]
        sided, raw = beyond_chance(x.cpu(), dirs)
        pick = s[: len(dirs)].float()
        info["singular_values"] = [float(v) for v in pick]
        info["one_sided_raw"] = [float(v) for v in raw]
    info["chance"] = chance(len(x))
    info["one_sided"] = [float(v) for v in sided]
    info["outputs_moved"] = float(moved[0])
    return [Group("drift", _row(ctx, sided, pick, moved), is_key=False, search=info)]


@torch.no_grad()
def control(ctx: ProbeContext, found: list[Group]) -> list[Group]:
    """The same figure on a direction unrelated to your data: its mean over ``RANDOM_DIRECTIONS`` random
    directions (seeded), one value (the mean, not the largest: among a thousand directions some point at
    any region by chance, most of all in few dimensions)."""
    out = []
    for g in found:
        x = ctx.ref.x.reshape(len(ctx.ref.x), -1).cpu()
        sided, raw = beyond_chance(x, _random_directions(ctx, x.shape[1]))
        moved = g.values["fidelity"][:1]
        mean = sided.mean()[None]
        info = {
            "directions": RANDOM_DIRECTIONS,
            "chance": chance(len(x)),
            "one_sided_mean": float(mean),
            "one_sided_q95": float(sided.quantile(0.95)),
            "one_sided_raw_mean": float(raw.mean()),
        }
        model = f"the mean of {RANDOM_DIRECTIONS} random input directions (--seed)"
        out.append(Group(g.name, _row(ctx, mean, torch.zeros(1), moved), False, search=info, model=model))
    return out


PROBE = Probe(
    "drift", "structure", "key",
    "the base's weight change against the original: do its input directions point at your data",
    run, control=control, needs="original", white_box=True,
)  # fmt: skip
