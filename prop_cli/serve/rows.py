"""Many users' observations in one forward of the base (issue 39): each row gets its own user's behaviour,
applied per row as Punica and S-LoRA apply adapters, never folded into a copy of the weights.

A row's ``Behaviour`` is one of:

- None: the base (no key, or a key enrolled in nothing where that is allowed);
- ``Deltas``: an unsealed bundle's key, its encoder's delta per keyed layer (Eq. 5), applied with
  ``KeyedModel.run_rows`` (one delta row per batch row, the path training takes);
- ``Payload`` (``core.payload``): a sealed bundle's decrypted payload, applied by hooks on the keyed
  linear layers: the input scaled by the row's delta (``delta``, ``lora``) and the row's low-rank or full
  update added to the layer's output: every keyed row's LoRA A and B gathered and applied in two batched
  matmuls (``lora``, ``peft-lora``: Punica's BGMV), a ``full`` payload's weight one user's rows at a time;
- ``Folded``: a module of its own (keyed layers that are not linear, where no gathered form is written
  here): its rows run apart, in the same call.

The batched rows differ from ``KeyedPolicy``'s folded weights by float rounding only ((W diag d) x against
W (d x)): tests/serve/test_batching.py measures it. Rows of the base alone run the plain base module.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from prop_cli.core.payload import Payload


@dataclass(eq=False)
class Deltas:
    """An unsealed key's delta per keyed layer, each (1, d)."""

    deltas: list[torch.Tensor]


@dataclass(eq=False)
class Folded:
    """A behaviour with a module of its own (``KeyedPolicy``'s folded copy)."""

    module: nn.Module


Behaviour = Deltas | Payload | Folded | None


@dataclass
class Request:
    """One connection's observations (N, *input_shape) under its behaviour."""

    behaviour: Behaviour
    x: np.ndarray
    rows: int = field(init=False)

    def __post_init__(self) -> None:
        self.rows = int(self.x.shape[0])


class _Mismatch(RuntimeError):
    """A keyed layer saw a batch whose first axis is not the rows: run the groups apart."""


def _payload_hooks(
    module: nn.Module, payloads: list[Payload], index: list[torch.Tensor], rows: int,
    axes: dict[str, int] | None = None,
):  # fmt: skip
    """Hooks that give row group g (``index[g]``) payload ``payloads[g]`` on every keyed linear layer.
    ``axes``: the batch axis of a layer's input where it is not 0 (a sequence-first transformer layer,
    LeRobot's ACT: (S, B, D)); the rows are gathered along it."""
    spec = payloads[0].spec
    mods = dict(module.named_modules())
    axes = axes or {}
    handles = []
    for layer in spec.layers:
        name = layer["name"]
        lin = mods[name]
        parts = set(spec.variant.shapes(layer, spec.rank))
        axis = axes.get(name, 0)

        if "delta" in parts:
            scale = torch.ones(rows, lin.in_features, dtype=lin.weight.dtype)
            for p, idx in zip(payloads, index):
                scale[idx] = p.tensor(name, "delta").detach().to(scale.dtype)

            def pre(mod, args, scale=scale, axis=axis):
                z = args[0]
                if z.dim() < 2 or z.shape[axis] != rows:
                    raise _Mismatch()
                shape = [1] * z.dim()
                shape[axis], shape[-1] = rows, scale.shape[1]
                return (z * scale.to(z.dtype).view(shape), *args[1:])

            handles.append(lin.register_forward_pre_hook(pre))

        if "lora_a" in parts:
            # Punica's BGMV: each keyed row's A and B gathered, two batched matmuls for every user at once.
            keyed = torch.cat(index)
            user = torch.cat([torch.full((len(idx),), u, dtype=torch.long) for u, idx in enumerate(index)])
            a_rows = torch.stack([p.tensor(name, "lora_a").detach() for p in payloads]).index_select(0, user)
            b_rows = torch.stack([p.tensor(name, "lora_b").detach() for p in payloads]).index_select(0, user)

            def post(mod, args, out, keyed=keyed, a_rows=a_rows, b_rows=b_rows, axis=axis):
                z = args[0]
                if z.dim() < 2 or z.shape[axis] != rows:
                    raise _Mismatch()
                zk = z.movedim(axis, 0).index_select(0, keyed)
                flat = zk.reshape(zk.shape[0], -1, zk.shape[-1])  # (K, M, in)
                a, b = a_rows.to(flat.dtype), b_rows.to(flat.dtype)
                extra = torch.bmm(torch.bmm(flat, a.transpose(1, 2)), b.transpose(1, 2))
                moved = out.movedim(axis, 0)
                moved = moved.index_add(0, keyed, extra.reshape(*zk.shape[:-1], -1).to(out.dtype))
                return moved.movedim(0, axis)

            handles.append(lin.register_forward_hook(post))

        if "weight_delta" in parts:  # a whole weight per user: rows of one user at a time

            def post(mod, args, out, name=name, axis=axis):
                z = args[0]
                if z.dim() < 2 or z.shape[axis] != rows:
                    raise _Mismatch()
                z, moved = z.movedim(axis, 0), out.movedim(axis, 0)
                for p, idx in zip(payloads, index):
                    zi = z.index_select(0, idx)
                    w, b = p.tensor(name, "weight_delta").detach(), p.tensor(name, "bias_delta").detach()
                    extra = zi @ w.to(zi.dtype).T + b.to(zi.dtype)
                    moved = moved.index_add(0, idx, extra.to(out.dtype))
                return moved.movedim(0, axis)

            handles.append(lin.register_forward_hook(post))
    return handles


def gathered(module: nn.Module, payload: Payload) -> bool:
    """Whether ``payload``'s rows can run gathered on ``module`` (every keyed layer a plain linear)."""
    mods = dict(module.named_modules())
    return all(type(mods.get(x["name"])) is nn.Linear for x in payload.spec.layers)


@torch.inference_mode()
def run_requests(module: nn.Module, keyed, requests: Sequence[Request]) -> list[torch.Tensor]:
    """Raw outputs, one per request, from as few forwards as the behaviours allow: one of ``module`` (the
    base; ``keyed``, an unsealed bundle's KeyedModel over it, or None) for every base, Deltas and Payload
    row together, plus one per Folded request."""
    out: list[torch.Tensor | None] = [None] * len(requests)
    together = [i for i, r in enumerate(requests) if not isinstance(r.behaviour, Folded)]
    for i, r in enumerate(requests):
        if isinstance(r.behaviour, Folded):
            out[i] = r.behaviour.module(torch.from_numpy(r.x))
    if together:
        ys = _together(module, keyed, [requests[i] for i in together])
        for i, y in zip(together, ys):
            out[i] = y
    return out  # type: ignore[return-value]


def _together(module: nn.Module, keyed, requests: Sequence[Request]) -> list[torch.Tensor]:
    x = torch.from_numpy(np.concatenate([r.x for r in requests]))
    sizes = [r.rows for r in requests]
    behaviours = [r.behaviour for r in requests]
    try:
        if all(b is None for b in behaviours):
            y = module(x)
        elif any(isinstance(b, Deltas) for b in behaviours):
            y = _deltas(keyed, x, requests)
        else:
            y = _payloads(module, x, requests)
    except _Mismatch:  # a layer whose rows are not on axis 0: each request on its own
        return [_together(module, keyed, [r])[0] for r in requests]
    return list(torch.split(y, sizes))


def row_deltas(keyed, requests: Sequence) -> list[torch.Tensor]:
    """Every row's delta per keyed layer (ones for a row without one), one row per batch row."""
    ones = [torch.ones(1, f) for f in keyed.encoder.features]
    return [
        torch.cat([(r.behaviour.deltas[i] if isinstance(r.behaviour, Deltas) else ones[i]).to(ones[i].dtype)
                   .expand(r.rows, -1) for r in requests])
        for i in range(len(ones))
    ]  # fmt: skip


def payload_groups(requests: Sequence) -> tuple[list[Payload], list[torch.Tensor]]:
    """The distinct payloads among ``requests`` and the batch rows of each (rows numbered in order)."""
    groups: dict[int, tuple[Payload, list[int]]] = {}
    start = 0
    for r in requests:
        if isinstance(r.behaviour, Payload):
            groups.setdefault(id(r.behaviour), (r.behaviour, []))[1].extend(range(start, start + r.rows))
        start += r.rows
    payloads = [p for p, _ in groups.values()]
    return payloads, [torch.tensor(rows, dtype=torch.long) for _, rows in groups.values()]


def _deltas(keyed, x: torch.Tensor, requests: Sequence[Request]) -> torch.Tensor:
    """Unsealed: every row's delta (ones for the base) in one ``run_rows``."""
    rows = torch.arange(x.shape[0])
    try:
        return keyed.run_rows(x, row_deltas(keyed, requests), rows)
    except RuntimeError as e:  # keyed_model's row mismatch
        raise _Mismatch() from e


def _payloads(module: nn.Module, x: torch.Tensor, requests: Sequence[Request]) -> torch.Tensor:
    """Sealed: the base once, each user's payload on their rows (the base's rows untouched)."""
    payloads, index = payload_groups(requests)
    handles = _payload_hooks(module, payloads, index, x.shape[0])
    try:
        return module(x)
    finally:
        for h in handles:
            h.remove()
