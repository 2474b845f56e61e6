"""Which linear layers get a key transform: matching as in peft (exact name, dotted suffix, regex)."""

from __future__ import annotations

import re

from torch import nn

from prop_cli.constants import DEFAULT_LAYERS_ATTR
from prop_cli.errors import PropError

ALL_LINEAR = "all-linear"
__all__ = ["ALL_LINEAR", "DEFAULT_LAYERS_ATTR", "default_layers", "linear_layers", "select_layers"]


def linear_layers(module: nn.Module) -> list[tuple[str, nn.Linear]]:
    """Every ``nn.Linear`` in module order (the order a chain model applies them)."""
    return [(name, m) for name, m in module.named_modules() if isinstance(m, nn.Linear)]


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


def _matches(pattern: str, name: str, all_names: list[str]) -> bool:
    """peft's rule: the exact name, a dotted suffix of it, or a regex matching the whole name.

    ``all-linear`` is every linear layer but the output head (the last one in module order).
    """
    if pattern == ALL_LINEAR:
        return name != all_names[-1] or len(all_names) == 1
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
    """Names of the linear layers to key, in module order; validated before the model is touched."""
    names = [n for n, _ in linear_layers(module)]
    if not names:
        raise PropError("the model has no nn.Linear layers", "prop keys linear layers only")
    listing = ", ".join(names[:20]) + (f" (+{len(names) - 20} more)" if len(names) > 20 else "")

    def check(p: str, which: str) -> None:
        if any(_matches(p, n, names) for n in names):
            return
        try:
            re.compile(p)
            bad_regex = ""
        except re.error as e:
            bad_regex = f" and is not a valid regex ({e})"
        raise PropError(
            f"{which} {p!r} matches no linear layer{bad_regex}",
            f"use an exact name, a dotted suffix, a regex or {ALL_LINEAR}; linear layers: {listing}",
        )

    if not patterns:
        # An adapter may name its own default (DEFAULT_LAYERS_ATTR on the module, e.g. SB3 CnnPolicy).
        own = getattr(module, DEFAULT_LAYERS_ATTR, None)
        chosen = [n for n in names if n in own] if own else default_layers(names)
    else:
        for p in patterns:
            check(p, flag)
        chosen = [n for n in names if any(_matches(p, n, names) for p in patterns)]
    for p in exclude or []:
        check(p, "--exclude")
        chosen = [n for n in chosen if not _matches(p, n, names)]
    if not chosen:
        raise PropError(f"{flag}/--exclude leave no layer to key", f"linear layers: {listing}")
    return chosen
