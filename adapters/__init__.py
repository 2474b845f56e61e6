"""Checkpoint adapters: a checkpoint -> a ``torch.nn.Module`` with the checkpoint's own names.

The contract is ``base.Adapter``; ``ADAPTERS`` is the registry, in the order formats are tried: the
first adapter whose ``recognise`` accepts a path loads it. A new format is one new file and one line
here. A format's helpers sit beside it (``sb3/``: the zip reader and VecNormalize statistics;
``lerobot/``: the policy protocol and its flat array view); ``hub`` fetches ``hf://`` paths.
(Until 0.1.x this package was installed as ``prop_adapters``; that name still imports, with a warning.)
"""

from __future__ import annotations

from pathlib import Path

import torch

from prop_cli.core.layers import keyable_layers
from prop_cli.core.rules import declare_model_fields
from prop_cli.errors import PropError, brief

from .base import (
    CODE_FIELD,
    TRUST_FLAG,
    Adapter,
    CheckpointOptions,
    LoadedModel,
    check_exists,
    names_code,
    require_trust,
)
from .folder import CONFIG, WEIGHTS, FolderAdapter
from .lerobot import LeRobotAdapter
from .mlp import MLPAdapter
from .module import ModuleAdapter
from .sb3 import SB3Adapter
from .weights import read_weights

ADAPTERS: list[Adapter] = [
    LeRobotAdapter(),  # before FolderAdapter: a LeRobot folder is also config.json + model.safetensors
    FolderAdapter(),
    SB3Adapter(),
    ModuleAdapter(),
    MLPAdapter(),
]
for _adapter in ADAPTERS:  # what each one's model spec holds, for the bundle format's checks
    declare_model_fields(_adapter.name, _adapter.manifest_fields, _adapter.check_spec)

__all__ = [
    "ADAPTERS",
    "CODE_FIELD",
    "Adapter",
    "CheckpointOptions",
    "LoadedModel",
    "TRUST_FLAG",
    "adapter_named",
    "check_arch_applies",
    "describe",
    "load_checkpoint",
    "names_code",
    "read_weights",
    "rebuild",
    "remote_code",
    "require_trust",
]


def adapter_named(name: str | None, source: str) -> Adapter:
    for a in ADAPTERS:
        if a.name == name:
            return a
    raise PropError(
        f"{source}: unknown model adapter '{name}' (known: {', '.join(a.name for a in ADAPTERS)})",
        "the bundle was written by a newer prop; upgrade prop",
    )


def _require_linear(loaded: LoadedModel) -> LoadedModel:
    if not keyable_layers(loaded.module):
        raise PropError(
            f"no linear layers or convolutions in {loaded.source}",
            "prop adds keys to nn.Linear and nn.Conv1d/2d/3d layers; use a model that has at least one",
        )
    return loaded


def _check_options(adapter: Adapter, options: CheckpointOptions, path: Path) -> None:
    for name in options.given():
        if name not in adapter.options:
            flag = CheckpointOptions.FLAGS[name]
            uses = " and ".join(CheckpointOptions.FLAGS[o] for o in adapter.options) or "no options"
            raise PropError(
                f"{flag} does not apply to {adapter.summary.split(':')[0]} ({path})",
                f"drop {flag}: that format takes {uses}",
            )


def load_checkpoint(
    path: str | Path,
    options: CheckpointOptions | None = None,
    *,
    arch: str | None = None,
    arch_kwargs: dict | None = None,
    activation: str | None = None,
    trust_remote_code: bool = False,
) -> LoadedModel:
    """Load a checkpoint with the first registered adapter that recognises it. Code the checkpoint's
    files name (a folder's entry point, LeRobot processor steps) runs only with ``trust_remote_code``."""
    options = options or CheckpointOptions(arch, arch_kwargs, activation, trust_remote_code)
    path = Path(path)
    check_exists(path)
    if path.is_dir() and not (path / CONFIG).exists() and (path / WEIGHTS).is_file():
        path = path / WEIGHTS  # a bare weights folder: read it as the file
    for adapter in ADAPTERS:
        if adapter.recognise(path, options):
            _check_options(adapter, options, path)
            named = adapter.remote_code_at(path, options)
            require_trust(named, f"checkpoint {path}", options.trust_remote_code)
            loaded = adapter.load(path, options)
            return _require_linear(loaded)
    read_weights(path)  # names what is wrong with the file (extension, content)
    raise PropError(f"checkpoint {path} is in no format prop reads", "`prop formats` lists them")


def remote_code(spec: dict, source: str) -> list[str]:
    """What rebuilding ``spec`` would import or call that a file names (``Adapter.remote_code``)."""
    adapter = adapter_named(spec.get("adapter") if isinstance(spec, dict) else None, str(source))
    return adapter.remote_code(spec, str(source))


def rebuild(
    spec: dict, weights: dict[str, torch.Tensor], source: str, *, trust_remote_code: bool = False,
    arch: str | None = None,
) -> LoadedModel:  # fmt: skip
    """Rebuild the module a bundle describes (``spec`` from its manifest) with ``weights``. Code the spec
    names (``remote_code``) is imported only with ``trust_remote_code``; otherwise nothing is. ``arch``:
    the user's own ``--arch`` for this command, called instead of the recorded ``model.arch`` (the only
    code a module or folder bundle names, so it needs no trust; its JSON arch_kwargs are handed to it)."""
    adapter = adapter_named(spec.get("adapter") if isinstance(spec, dict) else None, str(source))
    check_arch_applies(spec, source, arch)
    if arch is None:
        require_trust(adapter.remote_code(spec, str(source)), f"bundle {source}", trust_remote_code)
    given = {} if arch is None else {"arch": arch}
    try:
        return _require_linear(adapter.rebuild(spec, weights, str(source), **given))
    except KeyError as e:
        raise PropError(
            f"{source}: model spec lacks field {e}", "the manifest is damaged; re-create the bundle"
        ) from None
    except (TypeError, ValueError, IndexError, AttributeError, RuntimeError, OverflowError) as e:
        # A spec the adapter cannot build from (the manifest passed its schema, so it was edited).
        raise PropError(
            f"{source}: the model spec in the manifest does not build ({brief(e)})",
            "the manifest is damaged; re-create the bundle",
        ) from None


def check_arch_applies(spec: dict, source: str, arch: str | None) -> None:
    """``--arch`` on a bundle command replaces the recorded factory of bundles built by one (module and
    folder adapters); any other bundle rebuilds from its own files, and the flag is refused."""
    if arch is None:
        return
    adapter = adapter_named(spec.get("adapter") if isinstance(spec, dict) else None, str(source))
    if "arch" not in adapter.options:
        raise PropError(
            f"--arch does not apply to bundle {source}: its model is a {adapter.name} checkpoint, rebuilt "
            "from the bundle's own files",
            "drop --arch",
        )


def describe(loaded: LoadedModel) -> dict:
    """What the checkpoint's adapter knows about it (algorithm, spaces, bounds, activation, ...)."""
    return adapter_named(loaded.spec.get("adapter"), loaded.source).describe(loaded)
