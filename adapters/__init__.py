"""Checkpoint adapters: a weights file -> a ``torch.nn.Module`` with the checkpoint's names.

Installed as ``prop_adapters`` (``adapters`` is an unrelated PyPI package). A new format is one
new file exposing ``NAME``, ``from_weights(tensors, metadata, path, **options)`` and
``rebuild(spec, weights, source)``, plus one line in ``ADAPTERS``.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from prop_cli.errors import PropError

from . import mlp, module
from .base import LoadedModel, read_weights

ADAPTERS = {mlp.NAME: mlp, module.NAME: module}

__all__ = ["ADAPTERS", "LoadedModel", "load_checkpoint", "read_weights", "rebuild"]


def _require_linear(loaded: LoadedModel) -> LoadedModel:
    if not any(isinstance(m, nn.Linear) for m in loaded.module.modules()):
        raise PropError(
            f"no linear layers in {loaded.source}",
            "prop adds keys to nn.Linear layers; use a model that has at least one",
        )
    return loaded


def load_checkpoint(
    path: str | Path,
    *,
    arch: str | None = None,
    arch_kwargs: dict | None = None,
    activation: str | None = None,
) -> LoadedModel:
    """Load a checkpoint: with ``arch`` through the user's module class, else as a plain MLP."""
    tensors, metadata = read_weights(path)
    if arch:
        if activation is not None:
            raise PropError(
                "--activation only applies to plain MLP checkpoints",
                "drop --activation when using --arch (the class defines its activations)",
            )
        loaded = module.from_weights(tensors, metadata, path, arch=arch, arch_kwargs=arch_kwargs)
    else:
        if arch_kwargs:
            raise PropError("--arch-kwargs was given without --arch", "add --arch or drop it")
        loaded = mlp.from_weights(tensors, metadata, path, activation=activation)
    return _require_linear(loaded)


def rebuild(spec: dict, weights: dict[str, torch.Tensor], source: str) -> LoadedModel:
    """Rebuild the module a bundle describes (``spec`` from its manifest) with ``weights``."""
    name = spec.get("adapter") if isinstance(spec, dict) else None
    adapter = ADAPTERS.get(name)  # type: ignore[arg-type]
    if adapter is None:
        raise PropError(
            f"{source}: unknown model adapter '{name}' (known: {', '.join(ADAPTERS)})",
            "the bundle was written by a newer prop; upgrade prop",
        )
    try:
        return _require_linear(adapter.rebuild(spec, weights, str(source)))
    except KeyError as e:
        raise PropError(
            f"{source}: model spec lacks field {e}", "the manifest is damaged; re-create the bundle"
        ) from None
