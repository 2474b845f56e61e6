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
W (d x)): tests/serve/test_batching.py measures it. A no-key request runs the plain base module on its
own rows (its own forward, the original's output bit for bit) unless the server batches no-key rows too.
"""

from __future__ import annotations

import threading
import weakref
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


class RowMismatch(RuntimeError):
    """A keyed layer saw a batch whose first axis is not the rows: run the groups apart."""


def _payload_hooks(
    module: nn.Module, payloads: list[Payload], index: list[torch.Tensor], rows: int,
    axes: dict[str, int] | None = None, only: set[str] | None = None, parts: set[str] | None = None,
):  # fmt: skip
    """Hooks that give row group g (``index[g]``) payload ``payloads[g]`` on every keyed linear layer.
    ``axes``: the batch axis of a layer's input where it is not 0 (a sequence-first transformer layer,
    LeRobot's ACT: (S, B, D)); the rows are gathered along it. ``only``, ``parts``: these layers and parts
    alone (``_table_hooks`` leaves a ``full`` payload's weights to this)."""
    spec = payloads[0].spec
    mods = dict(module.named_modules())
    axes = axes or {}
    handles = []
    wanted = parts
    for layer in spec.layers:
        name = layer["name"]
        if only is not None and name not in only:
            continue
        lin = mods[name]
        parts = set(spec.variant.shapes(layer, spec.rank))
        if wanted is not None:
            parts &= wanted
        axis = axes.get(name, 0)

        if "delta" in parts:
            scale = torch.ones(rows, lin.in_features, dtype=lin.weight.dtype)
            for p, idx in zip(payloads, index):
                scale[idx] = p.tensor(name, "delta").detach().to(scale.dtype)
            handles.append(lin.register_forward_pre_hook(_scale_pre(scale, axis, rows)))

        if "lora_a" in parts:
            # Punica's BGMV: each keyed row's A and B gathered, two batched matmuls for every user at once.
            keyed = torch.cat(index)
            user = torch.cat([torch.full((len(idx),), u, dtype=torch.long) for u, idx in enumerate(index)])
            a_rows = torch.stack([p.tensor(name, "lora_a").detach() for p in payloads]).index_select(0, user)
            b_rows = torch.stack([p.tensor(name, "lora_b").detach() for p in payloads]).index_select(0, user)

            handles.append(lin.register_forward_hook(_lora_post(keyed, a_rows, b_rows, axis, rows)))

        if "weight_delta" in parts:  # a whole weight per user: rows of one user at a time

            def post(mod, args, out, name=name, axis=axis):
                z = args[0]
                if z.dim() < 2 or z.shape[axis] != rows:
                    raise RowMismatch()
                z, moved = z.movedim(axis, 0), out.movedim(axis, 0)
                for p, idx in zip(payloads, index):
                    zi = z.index_select(0, idx)
                    w, b = p.tensor(name, "weight_delta").detach(), p.tensor(name, "bias_delta").detach()
                    extra = zi @ w.to(zi.dtype).T + b.to(zi.dtype)
                    moved = moved.index_add(0, idx, extra.to(out.dtype))
                return moved.movedim(0, axis)

            handles.append(lin.register_forward_hook(post))
    return handles


class PayloadTable:
    """S-LoRA's unified memory pool, in small: each payload in use has a slot, and each keyed layer's
    deltas and LoRA A and B of every slot sit in one tensor (slot 0: the base, delta 1 and A, B 0). A batch
    then gathers its rows' tensors with one ``index_select`` per layer, however many users it holds
    (Punica's BGMV), instead of stacking every user's tensors again for every batch. A slot is taken
    when a payload first runs and given back when the payload is freed (evicted from the cache, its last
    connection closed). A ``full`` payload's whole weights stay out of the table (rows of one user at a
    time, ``_payload_hooks``)."""

    PARTS = ("delta", "lora_a", "lora_b")

    def __init__(self, spec, capacity: int = 16) -> None:
        self.spec = spec
        self.layers = {layer["name"]: spec.variant.shapes(layer, spec.rank) for layer in spec.layers}
        self.tables: dict[tuple[str, str], torch.Tensor] = {}
        for name, parts in self.layers.items():
            for part, shape in parts.items():
                if part in self.PARTS:
                    fill = torch.ones if part == "delta" else torch.zeros
                    self.tables[(name, part)] = fill(capacity, *shape)
        self.capacity = capacity
        self.slots: dict[int, int] = {}  # id(payload) -> slot
        self.free: list[int] = list(range(capacity - 1, 0, -1))
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self.slots)

    def slot(self, payload: Payload) -> int:
        with self._lock:
            found = self.slots.get(id(payload))
            if found is not None:
                return found
            if not self.free:
                self._grow()
            s = self.free.pop()
            with torch.no_grad():
                for (name, part), t in self.tables.items():
                    t[s] = payload.tensor(name, part).detach().to(t.dtype)
            self.slots[id(payload)] = s
        weakref.finalize(payload, self._release, id(payload), s)
        return s

    def _release(self, key: int, s: int) -> None:
        with self._lock:
            if self.slots.get(key) == s:
                del self.slots[key]
                self.free.append(s)

    def _grow(self) -> None:
        old = self.capacity
        self.capacity *= 2
        for k, t in self.tables.items():
            more = (torch.ones if k[1] == "delta" else torch.zeros)(old, *t.shape[1:])
            self.tables[k] = torch.cat([t, more])
        self.free.extend(range(2 * old - 1, old - 1, -1))

    def rows(self, requests: Sequence) -> torch.Tensor:
        """Each batch row's slot (0: a row without a payload)."""
        slots = [self.slot(r.behaviour) if isinstance(r.behaviour, Payload) else 0 for r in requests]
        sizes = [r.rows for r in requests]
        return torch.tensor(slots, dtype=torch.long).repeat_interleave(torch.tensor(sizes, dtype=torch.long))


def _table_hooks(module: nn.Module, table: PayloadTable, row_slot: torch.Tensor, requests: Sequence,
                 axes: dict[str, int] | None = None):  # fmt: skip
    """``_payload_hooks`` with each row's delta and LoRA gathered from ``table`` (one index_select per
    layer and part); a ``full`` payload's weights as there, one user's rows at a time."""
    mods = dict(module.named_modules())
    axes = axes or {}
    rows = int(row_slot.shape[0])
    keyed = torch.nonzero(row_slot).squeeze(1)
    keyed_slot = row_slot.index_select(0, keyed)
    handles = []
    full = [name for name, parts in table.layers.items() if "weight_delta" in parts]
    if full:
        payloads, index = payload_groups(requests)
        handles += _payload_hooks(module, payloads, index, rows, axes, only=set(full), parts={"weight_delta"})
    for name, parts in table.layers.items():
        lin, axis = mods[name], axes.get(name, 0)
        if "delta" in parts:
            scale = table.tables[(name, "delta")].index_select(0, row_slot)
            handles.append(lin.register_forward_pre_hook(_scale_pre(scale, axis, rows)))
        if "lora_a" in parts and len(keyed):
            a_rows = table.tables[(name, "lora_a")].index_select(0, keyed_slot)
            b_rows = table.tables[(name, "lora_b")].index_select(0, keyed_slot)
            handles.append(lin.register_forward_hook(_lora_post(keyed, a_rows, b_rows, axis, rows)))
    return handles


def _scale_pre(scale: torch.Tensor, axis: int, rows: int):
    """A forward pre-hook scaling each row's input (rows along ``axis``) by its row of ``scale``."""

    def pre(mod, args):
        z = args[0]
        if z.dim() < 2 or z.shape[axis] != rows:
            raise RowMismatch()
        shape = [1] * z.dim()
        shape[axis], shape[-1] = rows, scale.shape[1]
        return (z * (scale if scale.dtype == z.dtype else scale.to(z.dtype)).view(shape), *args[1:])

    return pre


def _lora_post(keyed: torch.Tensor, a_rows: torch.Tensor, b_rows: torch.Tensor, axis: int, rows: int):
    """A forward hook adding each keyed row's B (A x) (rows ``keyed`` along ``axis``) to the output.

    The output keeps the base layer's own layout (the update is added along ``axis`` in place, where no
    gradient is kept): a sequence-first layer's output moved to batch-first and back would leave the
    next layer a strided input, which cost ACT at its published size 12% of its forward at 8 rows
    (its next linear ran as a copy, ``mm`` and an add instead of one ``addmm``). Where every row is
    keyed, in order, nothing is gathered."""
    every = keyed.numel() == rows and torch.equal(keyed, torch.arange(rows))

    def post(mod, args, out):
        z = args[0]
        if z.dim() < 2 or z.shape[axis] != rows:
            raise RowMismatch()
        zk = z if every else z.index_select(axis, keyed)
        zk = zk.movedim(axis, 0) if axis else zk  # (K, ..., in)
        flat = zk.reshape(zk.shape[0], -1, zk.shape[-1])  # (K, M, in)
        a, b = a_rows, b_rows
        if a.dtype != flat.dtype:
            a, b = a.to(flat.dtype), b.to(flat.dtype)
        extra = torch.bmm(torch.bmm(flat, a.transpose(1, 2)), b.transpose(1, 2)).reshape(*zk.shape[:-1], -1)
        extra = extra.movedim(0, axis) if axis else extra  # the output's own axes (a view)
        if extra.dtype != out.dtype:
            extra = extra.to(out.dtype)
        if torch.is_grad_enabled():  # keep autograd's graph whole: out of place
            return out + extra if every else out.index_add(axis, keyed, extra)
        return out.add_(extra) if every else out.index_add_(axis, keyed, extra)

    return post


def gathered(module: nn.Module, payload: Payload) -> bool:
    """Whether ``payload``'s rows can run gathered on ``module`` (every keyed layer a plain linear)."""
    mods = dict(module.named_modules())
    return all(type(mods.get(x["name"])) is nn.Linear for x in payload.spec.layers)


def runs_alone(behaviour: Behaviour, batch_no_key: bool) -> bool:
    """Whether a request runs as its own forward: a ``Folded`` behaviour (a module of its own) always; a
    no-key request (None) unless ``batch_no_key``, so its output is the original's bit for bit: a matmul
    over more rows may be summed in another order by BLAS (its blocking depends on the batch size), which
    puts a batched base row within ~1e-7 of the original alone, not equal to it."""
    return isinstance(behaviour, Folded) or (behaviour is None and not batch_no_key)


@torch.inference_mode()
def run_requests(
    module: nn.Module, keyed, requests: Sequence[Request], table: PayloadTable | None = None,
    batch_no_key: bool = False,
) -> list[torch.Tensor]:  # fmt: skip
    """Raw outputs, one per request, from as few forwards as the behaviours allow: one of ``module`` (the
    base; ``keyed``, an unsealed bundle's KeyedModel over it, or None) for every Deltas and Payload row
    together, plus one per Folded request and one per no-key request (the original alone: bit for bit;
    ``batch_no_key``: no-key rows join the others, within float rounding). ``table``: the server's payload
    slots (a sealed bundle); without it each batch stacks its users' tensors."""
    out: list[torch.Tensor | None] = [None] * len(requests)
    together = [i for i, r in enumerate(requests) if not runs_alone(r.behaviour, batch_no_key)]
    for i, r in enumerate(requests):
        if isinstance(r.behaviour, Folded):
            out[i] = r.behaviour.module(torch.from_numpy(r.x))
        elif runs_alone(r.behaviour, batch_no_key):  # no key: the base on this request's rows alone
            out[i] = module(torch.from_numpy(r.x))
    if together:
        ys = _together(module, keyed, [requests[i] for i in together], table)
        for i, y in zip(together, ys):
            out[i] = y
    return out  # type: ignore[return-value]


def _together(module: nn.Module, keyed, requests: Sequence[Request], table=None) -> list[torch.Tensor]:
    x = torch.from_numpy(np.concatenate([r.x for r in requests]))
    sizes = [r.rows for r in requests]
    behaviours = [r.behaviour for r in requests]
    try:
        if all(b is None for b in behaviours):
            y = module(x)
        elif any(isinstance(b, Deltas) for b in behaviours):
            y = _deltas(keyed, x, requests)
        else:
            y = _payloads(module, x, requests, table)
    except RowMismatch:  # a layer whose rows are not on axis 0: each request on its own
        return [_together(module, keyed, [r], table)[0] for r in requests]
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
        raise RowMismatch() from e


def payload_handles(module: nn.Module, requests: Sequence, rows: int, table: PayloadTable | None,
                    axes: dict[str, int] | None = None) -> list:  # fmt: skip
    """The hooks that give each request's rows its payload: gathered from ``table``, or stacked."""
    if table is not None:
        return _table_hooks(module, table, table.rows(requests), requests, axes)
    payloads, index = payload_groups(requests)
    return _payload_hooks(module, payloads, index, rows, axes)


def _payloads(module: nn.Module, x: torch.Tensor, requests: Sequence[Request], table=None) -> torch.Tensor:
    """Sealed: the base once, each user's payload on their rows (the base's rows scaled by 1, 0 added)."""
    handles = payload_handles(module, requests, x.shape[0], table)
    try:
        return module(x)
    finally:
        for h in handles:
            h.remove()
