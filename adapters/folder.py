"""A model folder as the Hugging Face hub and LeRobot lay it out: ``config.json`` + ``model.safetensors``.

The module comes from a factory called as ``factory(config, **arch_kwargs)``, where ``config`` is the
parsed ``config.json`` (a dict). The factory is ``--arch package.module:factory``, or else the one an
installed package registers for the config's ``type`` (LeRobot) or ``model_type`` (Hugging Face)
in the entry-point group ``prop.architectures``, e.g. in the package's pyproject.toml::

    [project.entry-points."prop.architectures"]
    my_policy = "my_pkg.policies:build"

The manifest keeps the config and the factory's import path, so a bundle rebuilds without the
original folder (the package must still be importable).
"""

from __future__ import annotations

import json
from importlib.metadata import entry_points
from pathlib import Path

import torch
from torch import nn

from prop_cli.core.rules import RECORD, text
from prop_cli.errors import PropError

from .base import Adapter, CheckpointOptions, LoadedModel
from .module import fitted, load_strict, recorded_arch, resolve_factory
from .weights import read_weights

CONFIG = "config.json"
WEIGHTS = "model.safetensors"
SHARD_INDEX = "model.safetensors.index.json"
ENTRY_POINT_GROUP = "prop.architectures"
TYPE_FIELDS = ("type", "model_type")


def read_config(folder: Path) -> dict:
    path = folder / CONFIG
    try:
        config = json.loads(path.read_text())
    except (OSError, ValueError, RecursionError) as e:  # JSONDecodeError, UnicodeDecodeError: ValueErrors
        raise PropError(
            f"{path} is not readable JSON ({type(e).__name__})", "fix or re-export config.json"
        ) from None
    if not isinstance(config, dict):
        raise PropError(f"{path} is not a JSON object", "config.json must hold an object of settings")
    return config


def read_folder_weights(folder: Path) -> tuple[dict[str, torch.Tensor], str]:
    """Tensors of ``model.safetensors`` (or of its shards) and the path to name as their source."""
    single = folder / WEIGHTS
    if single.is_file():
        return read_weights(single)[0], str(single)
    index = folder / SHARD_INDEX
    if index.is_file():
        try:
            shards = sorted(set(json.loads(index.read_text())["weight_map"].values()))
        except (OSError, ValueError, KeyError, TypeError, AttributeError, RecursionError):
            raise PropError(
                f"{index} has no readable weight_map", "re-export the sharded checkpoint"
            ) from None
        tensors: dict[str, torch.Tensor] = {}
        for shard in shards:
            tensors.update(read_weights(folder / shard)[0])
        return tensors, str(folder)
    raise PropError(
        f"folder {folder} has no weights ({WEIGHTS} or {SHARD_INDEX})",
        f"put the model's weights next to {CONFIG} as {WEIGHTS}",
    )


def config_type(config: dict) -> str | None:
    for f in TYPE_FIELDS:
        if isinstance(config.get(f), str) and config[f]:
            return config[f]
    return None


def registered_builder(type_name: str) -> str | None:
    """``package.module:factory`` an installed package registers for ``type_name``, if any."""
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        if ep.name == type_name:
            return ep.value
    return None


def _builder(folder: Path, config: dict, arch: str | None) -> tuple[str, str]:
    if arch:
        return arch, "--arch"
    type_name = config_type(config)
    if type_name is None:
        raise PropError(
            f"{folder / CONFIG} has no 'type' or 'model_type', so prop cannot pick a builder",
            "pass --arch package.module:factory (called as factory(config, **arch_kwargs))",
        )
    value = registered_builder(type_name)
    if value is None:
        raise PropError(
            f"{folder}: no builder for config type '{type_name}' (no --arch, and no installed package "
            f"registers '{type_name}' in entry-point group '{ENTRY_POINT_GROUP}')",
            "pass --arch package.module:factory, or install the package that provides it",
        )
    return value, f"entry point '{type_name}'"


def build(
    spec: dict, weights: dict[str, torch.Tensor], source: str, arch: str | None = None,
    what: str | None = None, fix: str | None = None,
) -> LoadedModel:  # fmt: skip
    """The module ``arch`` (default: ``spec["arch"]``) builds from the config, with ``weights``."""
    arch, kwargs = arch or spec["arch"], dict(spec.get("arch_kwargs") or {})
    what = what or arch
    factory = resolve_factory(arch, what=what, fix=fix)

    def make() -> object:
        try:
            return factory(spec["config"], **kwargs)
        except Exception as e:
            raise PropError(
                f"{what}: calling it as factory(config, **arch_kwargs) failed ({type(e).__name__}: {e})",
                "the factory must take the parsed config.json (a dict) as its first argument",
            ) from None

    fix_fit = "check that config.json, --arch and --arch-kwargs belong to these weights"
    module = fitted(make, weights, source, f"the module {arch} builds", fix_fit)
    if not isinstance(module, nn.Module):
        raise PropError(
            f"{what} returned a {type(module).__name__}, not a torch.nn.Module", "return the model"
        )
    return load_strict(
        module,
        weights,
        spec,
        source,
        what=f"the module {arch} builds",
        fix=fix_fit,
    )


class FolderAdapter(Adapter):
    name = "folder"
    options = ("arch", "arch_kwargs")
    manifest_fields = {"arch": text(), "arch_kwargs": RECORD, "builder": text(), "config": RECORD}
    summary = (
        "a model folder: config.json + model.safetensors (Hugging Face / LeRobot layout, sharded too), "
        "built by factory(config, **arch_kwargs) from --arch or a package's 'prop.architectures' entry point"
    )

    def recognise(self, path: Path, options: CheckpointOptions) -> bool:
        return path.is_dir()

    def load(self, path: Path, options: CheckpointOptions) -> LoadedModel:
        if not (path / CONFIG).is_file():
            raise PropError(
                f"folder {path} has no {CONFIG}",
                f"pass a folder with {CONFIG} and {WEIGHTS}, or the weights file itself",
            )
        config = read_config(path)
        weights, source = read_folder_weights(path)
        value, via = _builder(path, config, options.arch)
        kwargs = dict(options.arch_kwargs or {})
        try:
            json.dumps(kwargs)
        except (TypeError, ValueError) as e:
            raise PropError(f"--arch-kwargs is not JSON-serialisable ({e})", "pass a JSON object") from None
        spec = {"adapter": self.name, "arch": value, "arch_kwargs": kwargs, "builder": via, "config": config}
        return build(spec, weights, source)

    def rebuild(
        self, spec: dict, weights: dict[str, torch.Tensor], source: str, arch: str | None = None
    ) -> LoadedModel:
        """``arch``: the user's --arch of this command instead of the recorded model.arch."""
        return build(spec, weights, source, *recorded_arch(spec, source, arch))

    def remote_code(self, spec: dict, source: str) -> list[str]:
        return [f"model.arch {spec.get('arch')!r} (called with model.config and model.arch_kwargs)"]

    def remote_code_at(self, path: Path, options: CheckpointOptions) -> list[str]:
        if options.arch or not (path / CONFIG).is_file():
            return []  # --arch is the user's own choice; a folder without config.json fails in load
        value, via = _builder(path, read_config(path), None)
        # The package is installed, but which of its entry points runs is chosen by config.json.
        return [f"{value!r}, the {via} that {CONFIG} selects"]

    def weights(self, path: Path) -> dict[str, torch.Tensor]:
        return read_folder_weights(path)[0] if path.is_dir() else read_weights(path)[0]

    def describe(self, loaded: LoadedModel) -> dict:
        info = super().describe(loaded)
        info.update(builder=loaded.spec.get("builder"), type=config_type(loaded.spec.get("config", {})))
        return info
