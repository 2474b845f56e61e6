"""Which layers get a key transform: matching as in peft (exact name, dotted suffix, regex), and what a
key transform is for each kind of layer.

Keyable layers are ``nn.Linear`` (paper Eq. 5: ``W diag(delta) z + b``, delta per input feature) and
``nn.Conv1d/2d/3d``, where Eq. 5 carries over as one delta per input channel: scaling channel c of
the input everywhere equals scaling the kernel's input-channel slice c (zero, reflect, replicate and
circular padding all commute with it), so a conv's key folds into its weights exactly as a linear
layer's does. Transposed convolutions are not keyed. The default choice and ``all-linear`` stay
linear-only (bundles and commands written before convolutions were keyable choose the same layers);
convolutions are chosen by name or regex, or by a policy's own default (LeRobot Diffusion's U-Net).
"""

from __future__ import annotations

import math
import re

import torch
from torch import nn

from prop_cli.constants import DEFAULT_LAYERS_ATTR
from prop_cli.errors import PropError

ALL_LINEAR = "all-linear"
CONVS = (nn.Conv1d, nn.Conv2d, nn.Conv3d)
KEYABLE = (nn.Linear, *CONVS)
__all__ = [
    "ALL_LINEAR",
    "DEFAULT_LAYERS_ATTR",
    "default_layers",
    "describe_layer",
    "in_width",
    "is_conv",
    "keyable_layers",
    "linear_layers",
    "scale_inputs",
    "select_layers",
]


def linear_layers(module: nn.Module) -> list[tuple[str, nn.Linear]]:
    """Every ``nn.Linear`` in module order (the order a chain model applies them)."""
    return [(name, m) for name, m in module.named_modules() if isinstance(m, nn.Linear)]


def keyable_layers(module: nn.Module) -> list[tuple[str, nn.Module]]:
    """Every linear and convolution layer (what a key can scale), in module order."""
    return [(name, m) for name, m in module.named_modules() if isinstance(m, KEYABLE)]


def is_conv(m: nn.Module) -> bool:
    return isinstance(m, CONVS)


def in_width(m: nn.Module) -> int:
    """Deltas per key for this layer: its input features (linear) or input channels (convolution)."""
    return m.in_channels if is_conv(m) else m.in_features


def out_width(m: nn.Module) -> int:
    return m.out_channels if is_conv(m) else m.out_features


def describe_layer(name: str, m: nn.Module) -> dict:
    """What `prop inspect` and a sealed payload's layout say of a layer. A convolution adds its kernel
    and groups (they fix its payload tensors' shapes); a linear layer's record is as before."""
    out = {"name": name, "in_features": in_width(m), "out_features": out_width(m)}
    if is_conv(m):
        out |= {"kernel": list(m.kernel_size), "groups": int(m.groups)}
    return out


def scale_inputs(w: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """The factor that scales weight ``w``'s inputs by ``d`` (one value per input feature or channel),
    shaped to broadcast over ``w``: (1, in) for a linear (out, in) weight; (1, in, 1, ...) for a
    convolution's (out, in / groups, *kernel), expanded per output channel's group where groups > 1."""
    if w.dim() == 2:
        return d[None, :]
    spatial = [1] * (w.dim() - 2)
    per_group = w.shape[1]
    groups = d.numel() // per_group
    if groups == 1:
        return d.view(1, per_group, *spatial)
    per_out = d.view(groups, per_group).repeat_interleave(w.shape[0] // groups, dim=0)
    return per_out.view(w.shape[0], per_group, *spatial)


def kernel_fan_in(layer: dict) -> int:
    """Weights per output channel of a layer as ``describe_layer`` records it (a LoRA A's width)."""
    return int(layer["in_features"]) // int(layer.get("groups", 1)) * math.prod(layer.get("kernel", [1]))


def default_layers(names: list[str]) -> list[str]:
    """Every linear layer but the first; a model with one linear layer keys that one.

    The first layer's input is the raw observation: scaling it only re-weights input features. Measured
    by ``examples/layer_choice.py`` (default settings, 2 seeds) against first only, last only,
    all-linear and all: on IL, all-but-first ties the best personalization (0.9991) with the lowest
    leakage (1-bit neighbours mean 0.0037 / worst 0.0084, worst random key 0.023; first only reaches
    0.87 personalization); on digits, last only personalizes 2/144 samples better (0.972 vs 0.958) but
    leaks (0.007) where all-but-first leaks nothing. Figures in CHANGELOG.md.
    """
    return names[1:] if len(names) > 1 else list(names)


def _matches(pattern: str, name: str, linear: list[str]) -> bool:
    """peft's rule: the exact name, a dotted suffix of it, or a regex matching the whole name.

    ``all-linear`` is every linear layer (``linear``: their names) but the output head (the last one
    in module order).
    """
    if pattern == ALL_LINEAR:
        return name in linear and (name != linear[-1] or len(linear) == 1)
    if name == pattern or name.endswith("." + pattern):
        return True
    try:
        return re.fullmatch(pattern, name) is not None
    except re.error:
        return False


def select_layers(
    module: nn.Module,
    patterns: list[str] | None = None,
    exclude: list[str] | None = None,
    flag: str = "--layers",
) -> list[str]:
    """Names of the layers to key (linear and convolution), in module order; validated before the model
    is touched."""
    linear = [n for n, _ in linear_layers(module)]
    names = [n for n, _ in keyable_layers(module)]
    if not names:
        raise PropError(
            "the model has no nn.Linear or nn.Conv1d/2d/3d layers", "prop keys linear layers and convolutions"
        )
    listing = ", ".join(names[:20]) + (f" (+{len(names) - 20} more)" if len(names) > 20 else "")

    def check(p: str, which: str) -> None:
        if any(_matches(p, n, linear) for n in names):
            return
        try:
            re.compile(p)
            bad_regex = ""
        except re.error as e:
            bad_regex = f" and is not a valid regex ({e})"
        raise PropError(
            f"{which} {p!r} matches no linear layer or convolution{bad_regex}",
            f"use an exact name, a dotted suffix, a regex or {ALL_LINEAR}; layers: {listing}",
        )

    if not patterns:
        # An adapter may name its own default (DEFAULT_LAYERS_ATTR on the module, e.g. SB3 CnnPolicy).
        own = getattr(module, DEFAULT_LAYERS_ATTR, None)
        if not own and not linear:  # the default choice is linear-only (bundles before keyed convolutions)
            raise PropError(
                "the model has no nn.Linear layers, which the default choice keys",
                f"name the convolutions to key with {flag} (layers: {listing})",
            )
        chosen = [n for n in names if n in own] if own else default_layers(linear)
    else:
        for p in patterns:
            check(p, flag)
        chosen = [n for n in names if any(_matches(p, n, linear) for p in patterns)]
    for p in exclude or []:
        check(p, "--exclude")
        chosen = [n for n in chosen if not _matches(p, n, linear)]
    if not chosen:
        raise PropError(f"{flag}/--exclude leave no layer to key", f"layers: {listing}")
    return chosen
