"""Checkpoint adapters: a weights file -> a ``torch.nn.Module`` with the checkpoint's names.

Installed as ``prop_adapters`` (``adapters`` is an unrelated PyPI package). A new format is one
new file exposing ``NAME``, a loader (``from_weights(tensors, metadata, path, **options)`` for a
weights file, ``load(path, **options)`` for a container: sb3 zips, model folders) and
``rebuild(spec, weights, source)``, plus one line in ``ADAPTERS``.

``load_checkpoint`` dispatches on the path: a directory -> ``folder`` (config.json +
model.safetensors; a folder with only model.safetensors is read as that file), ``.zip`` -> ``sb3``,
any other file -> ``module`` with ``--arch``, else ``mlp``.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from prop_cli.errors import PropError

from . import folder, mlp, module, sb3
from .base import LoadedModel, read_weights

ADAPTERS = {mlp.NAME: mlp, module.NAME: module, sb3.NAME: sb3, folder.NAME: folder}

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
    """Load a checkpoint: an SB3 zip, a model folder, or a weights file (``arch``'s class or a plain MLP)."""
    path = Path(path)
    if path.is_dir() and not (path / folder.CONFIG).exists() and (path / folder.WEIGHTS).is_file():
        path = path / folder.WEIGHTS  # a bare weights folder: read it as the file
    if path.is_dir():
        if activation is not None:
            raise PropError(
                "--activation does not apply to a model folder",
                "drop it: the module the builder returns defines its activations",
            )
        return _require_linear(folder.load(path, arch=arch, arch_kwargs=arch_kwargs))
    if path.suffix.lower() == ".zip":
        if arch or arch_kwargs:
            raise PropError(
                "--arch/--arch-kwargs do not apply to a Stable-Baselines3 zip",
                "drop them: prop rebuilds the policy from the zip itself",
            )
        return _require_linear(sb3.load(path, activation=activation))
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
