"""A user's payload in a sealed bundle: what turns the public base into their behaviour.

Kinds (``KINDS``: one class each), per keyed linear layer with weight W (out, in):

- ``delta``: a scale per input feature, W diag(delta): the paper's Eq. 5 with delta stored
  instead of produced by a key encoder.
- ``lora``: (W + B A) diag(delta), B (out, r) and A (r, in): Eq. 5 plus a low-rank update.
- ``full``: W + D and b + d: every weight of the keyed layers.
- ``peft-lora``: W + B A, no delta: exactly peft's LoRA (``lora_alpha = r``, so its scaling is 1), so
  the key's holder can export it as a standard peft adapter (``prop_cli.deploy.peft``). ``lora``'s
  per-input delta makes its update full-rank, which no peft LoRA can hold.

A keyed convolution (weight (out, in / groups, *kernel)) has one delta per input channel; its LoRA
update is low-rank in the flattened kernel, B (out, r) A (r, in / groups * prod(kernel)) reshaped to
the weight: the same update as peft's convolution LoRA (A a conv with the layer's kernel, B a 1x1
conv), merged. ``full`` adds a tensor of the weight's shape.

Every kind starts at the base behaviour (delta = 1, B = 0, D = 0). The payload is applied with
weight parametrizations, so the module tree and its state-dict names stay the checkpoint's, and
it works where a layer's weight is read without calling the layer (e.g. attention projections).
For inference it is folded into a copy of the weights in memory; never write that copy to disk.
"""

from __future__ import annotations

import contextlib
import copy
import math
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from typing import ClassVar

import torch
from torch import nn
from torch.nn.utils import parametrize

from prop_cli.config import PAYLOAD_KINDS
from prop_cli.errors import PropError

from .layers import kernel_fan_in, scale_inputs


class PayloadKind:
    """One kind of payload (as peft's LoRA variants): the tensors it keeps per keyed layer and how they
    change that layer's weight and bias. Every kind starts at the base behaviour."""

    name: ClassVar[str]
    has_rank: ClassVar[bool] = False  # takes --payload-rank
    changes_bias: ClassVar[bool] = False  # adds a bias delta (its layers' biases must be reachable)
    peft_lora: ClassVar[bool] = False  # exactly a peft LoRA adapter (prop export --peft)

    @classmethod
    def rank(cls, requested: int) -> int:
        """The rank a bundle records for ``--payload-rank requested``: 0 for kinds without one."""
        return requested if cls.has_rank else 0

    @classmethod
    def shapes(cls, layer: dict, rank: int) -> dict[str, tuple[int, ...]]:
        """Part name -> shape of the tensors this kind keeps for one keyed layer (``describe_layer``)."""
        raise NotImplementedError

    @classmethod
    def weight(cls, payload: Payload, layer: str, w: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    @classmethod
    def bias_delta(cls, payload: Payload, layer: str) -> torch.Tensor | None:
        """What the payload adds to the layer's bias; None where the kind leaves biases alone."""
        return None


class Delta(PayloadKind):
    """W diag(delta): the paper's Eq. 5 with delta stored instead of produced by a key encoder."""

    name = "delta"

    @classmethod
    def shapes(cls, layer: dict, rank: int) -> dict[str, tuple[int, ...]]:
        return {"delta": (int(layer["in_features"]),)}

    @classmethod
    def weight(cls, payload: Payload, layer: str, w: torch.Tensor) -> torch.Tensor:
        return w * scale_inputs(w, payload.tensor(layer, "delta"))


class PeftLoRA(PayloadKind):
    """W + B A, no delta: exactly peft's LoRA (lora_alpha = r)."""

    name = "peft-lora"
    has_rank = True
    peft_lora = True

    @classmethod
    def shapes(cls, layer: dict, rank: int) -> dict[str, tuple[int, ...]]:
        return {"lora_a": (rank, kernel_fan_in(layer)), "lora_b": (int(layer["out_features"]), rank)}

    @classmethod
    def weight(cls, payload: Payload, layer: str, w: torch.Tensor) -> torch.Tensor:
        update = payload.tensor(layer, "lora_b") @ payload.tensor(layer, "lora_a")
        return w + (update if w.dim() == 2 else update.view_as(w))


class LoRA(PayloadKind):
    """(W + B A) diag(delta): Eq. 5 plus a low-rank update (full-rank with delta: no peft LoRA)."""

    name = "lora"
    has_rank = True

    @classmethod
    def shapes(cls, layer: dict, rank: int) -> dict[str, tuple[int, ...]]:
        return {**Delta.shapes(layer, rank), **PeftLoRA.shapes(layer, rank)}

    @classmethod
    def weight(cls, payload: Payload, layer: str, w: torch.Tensor) -> torch.Tensor:
        return Delta.weight(payload, layer, PeftLoRA.weight(payload, layer, w))


class Full(PayloadKind):
    """W + D and b + d: every weight of the keyed layers."""

    name = "full"
    changes_bias = True

    @classmethod
    def shapes(cls, layer: dict, rank: int) -> dict[str, tuple[int, ...]]:
        i, o = int(layer["in_features"]), int(layer["out_features"])
        kernel = tuple(int(k) for k in layer.get("kernel", ()))
        weight = (o, i // int(layer.get("groups", 1)), *kernel) if kernel else (o, i)
        return {"weight_delta": weight, "bias_delta": (o,)}

    @classmethod
    def weight(cls, payload: Payload, layer: str, w: torch.Tensor) -> torch.Tensor:
        return w + payload.tensor(layer, "weight_delta")

    @classmethod
    def bias_delta(cls, payload: Payload, layer: str) -> torch.Tensor | None:
        return payload.tensor(layer, "bias_delta")


# The kinds by the name a manifest records; the CLI's --payload choices (config.PAYLOAD_KINDS) are these.
KINDS: dict[str, type[PayloadKind]] = {k.name: k for k in (LoRA, Delta, Full, PeftLoRA)}
assert tuple(KINDS) == PAYLOAD_KINDS, "config.PAYLOAD_KINDS names the kinds defined here"


def payload_kind(name: str) -> type[PayloadKind]:
    if name not in KINDS:
        raise PropError(f"--payload {name!r} is unknown", f"use one of {', '.join(KINDS)}")
    return KINDS[name]


@dataclass
class PayloadSpec:
    kind: str
    # [{"name": str, "in_features": int, "out_features": int}] in module order; a convolution's record
    # adds "kernel" (its sizes) and "groups" (core.layers.describe_layer)
    layers: list[dict]
    rank: int = 0  # kinds with a rank only

    @property
    def variant(self) -> type[PayloadKind]:
        return payload_kind(self.kind)

    def validate(self) -> PayloadSpec:
        if self.variant.has_rank and self.rank < 1:
            raise PropError(f"--payload-rank {self.rank} is invalid", "--payload-rank must be at least 1")
        if not self.layers:
            raise PropError("the payload has no keyed layers", "choose layers with --layers")
        return self

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> PayloadSpec:
        return cls(kind=str(d["kind"]), layers=[dict(x) for x in d["layers"]], rank=int(d.get("rank", 0)))


def payload_elements(spec: PayloadSpec) -> int:
    """How many numbers a payload of ``spec`` holds, computed from the layout (nothing allocated)."""
    return sum(math.prod(shape) for shape in _tensor_shapes(spec).values())


def _tensor_shapes(spec: PayloadSpec) -> dict[str, tuple[int, ...]]:
    return {
        f"{layer['name']}.{part}": shape
        for layer in spec.layers
        for part, shape in spec.variant.shapes(layer, spec.rank).items()
    }


class Payload(nn.Module):
    """The trainable tensors of one user's payload, by ``<layer>.<part>`` name."""

    def __init__(self, spec: PayloadSpec, generator: torch.Generator | None = None) -> None:
        super().__init__()
        self.spec = spec.validate()
        self.params = nn.ParameterDict()
        # ParameterDict keys may not contain dots: index them, and keep the names beside.
        self._keys: dict[str, str] = {}
        for name, shape in _tensor_shapes(spec).items():
            part = name.rsplit(".", 1)[1]
            if part == "delta":
                t = torch.ones(shape)
            elif part == "lora_a":  # random A, zero B: the product starts at zero but both get gradients
                t = torch.randn(shape, generator=generator) / shape[1] ** 0.5
            else:
                t = torch.zeros(shape)
            self._keys[name] = f"p{len(self._keys)}"
            self.params[self._keys[name]] = nn.Parameter(t)

    def tensor(self, layer: str, part: str) -> torch.Tensor:
        return self.params[self._keys[f"{layer}.{part}"]]

    def weight(self, layer: str, w: torch.Tensor) -> torch.Tensor:
        return self.spec.variant.weight(self, layer, w)

    def bias_delta(self, layer: str) -> torch.Tensor | None:
        """What the payload adds to ``layer``'s bias (its kind says; None: the bias stays the base's)."""
        return self.spec.variant.bias_delta(self, layer)

    def tensors(self) -> dict[str, torch.Tensor]:
        return {name: self.params[k].detach().cpu() for name, k in self._keys.items()}

    @classmethod
    def from_tensors(cls, spec: PayloadSpec, tensors: dict[str, torch.Tensor]) -> Payload:
        want = _tensor_shapes(spec)
        got = {k: tuple(v.shape) for k, v in tensors.items()}
        if got != want:
            raise PropError(
                "a sealed payload does not match the bundle's keyed layers",
                "the bundle is damaged or was edited; restore it from a trusted copy",
            )
        p = cls(spec)
        with torch.no_grad():
            for k, v in tensors.items():
                p.params[p._keys[k]].copy_(v)
        return p

    @contextlib.contextmanager
    def attached(self, module: nn.Module) -> Iterator[nn.Module]:
        """``module`` computes with the payload applied (differentiably) inside the block."""
        mods = dict(module.named_modules())
        done: list[tuple[nn.Module, list[str]]] = []
        try:
            for layer in self.spec.layers:
                lin = mods[layer["name"]]
                done.append((lin, list(lin._parameters)))
                parametrize.register_parametrization(lin, "weight", _Weight(self, layer["name"]))
                if self.spec.variant.changes_bias:
                    parametrize.register_parametrization(lin, "bias", _Bias(self, layer["name"]))
            yield module
        finally:
            for lin, order in done:
                for attr in list(getattr(lin, "parametrizations", {}).keys()):
                    parametrize.remove_parametrizations(lin, attr, leave_parametrized=False)
                # Removing a parametrization re-registers the tensor last; keep the state-dict order.
                lin._parameters = {k: lin._parameters[k] for k in order}

    @torch.no_grad()
    def fold(self, module: nn.Module) -> nn.Module:
        """A plain copy of ``module`` with the payload folded into its weights (in memory only). Only the
        keyed layers' weights and biases are copies; every other tensor is ``module``'s own (a 450 M-
        parameter policy folds in megabytes, not another 1.8 GB)."""
        own = dict(module.named_modules())
        keyed = {id(t) for x in self.spec.layers for t in (own[x["name"]].weight, own[x["name"]].bias)}
        shared = {id(t): t for t in (*module.parameters(), *module.buffers()) if id(t) not in keyed}
        folded = copy.deepcopy(module, shared)
        mods = dict(folded.named_modules())
        for layer in self.spec.layers:
            lin = mods[layer["name"]]
            lin.weight.copy_(self.weight(layer["name"], lin.weight).to(lin.weight.dtype))  # or a conv's
            delta = self.bias_delta(layer["name"])
            if delta is not None and lin.bias is not None:
                lin.bias.add_(delta.to(lin.bias.dtype))
        return folded


class _Weight(nn.Module):
    def __init__(self, payload: Payload, layer: str) -> None:
        super().__init__()
        # A plain attribute, not a submodule: the payload must not join the base's state dict.
        object.__setattr__(self, "payload", payload)
        self.layer = layer

    def forward(self, w: torch.Tensor) -> torch.Tensor:
        # In the base's dtype (a bf16 layer: pi0's expert as published, or a base held bf16 under
        # --precision bf16), as ``fold`` writes it: a parametrization may not change the dtype.
        return self.payload.weight(self.layer, w).to(w.dtype)


class _Bias(_Weight):
    def forward(self, b: torch.Tensor) -> torch.Tensor:
        return (b + self.payload.bias_delta(self.layer)).to(b.dtype)
