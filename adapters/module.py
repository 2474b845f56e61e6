"""The user's own module class: ``--arch package.module:factory`` (or ``path/to/file.py:factory``) plus
JSON keyword arguments.

A module name is imported from the folder prop runs in (first on the path, as ``python -m`` does), then
``PYTHONPATH`` and installed packages; a ``.py`` path is loaded from that file (relative to the folder
prop runs in). The bundle records ``--arch`` as given, so later commands need the same module where
they run, or ``--arch`` again naming it from there (``prop run``, ``eval``, ``attack``, ``export``, ...).
"""

from __future__ import annotations

import importlib
import json
import os
import sys
from collections.abc import Callable
from pathlib import Path

import torch
from torch import nn

from prop_cli.core.rules import RECORD, text
from prop_cli.errors import PropError

from .base import Adapter, CheckpointOptions, LoadedModel, finish
from .weights import is_weights_file, read_weights

ARCH_FORMAT = (
    "give --arch as package.module:factory or path/to/file.py:factory, e.g. mypolicies.nets:make_policy"
)


def resolve_factory(arch: str, *, what: str | None = None, fix: str | None = None):
    """Import ``package.module:attr.path`` (or ``path/to/file.py:attr``) and return the attribute (a class
    or function). ``what`` names it in errors (default ``--arch 'ARCH'``); ``fix``: what to do when the
    module or file is not found (default: where to run prop from)."""
    what = what or f"--arch '{arch}'"
    # The last ':' splits, so a Windows drive letter stays in the path.
    mod_name, sep, attr = arch.rpartition(":")
    if not sep or not mod_name or not attr:
        raise PropError(f"{what} is not of the form package.module:factory", ARCH_FORMAT)
    obj = code_attribute(import_code(mod_name, what, fix), attr)
    if obj is None:
        raise PropError(f"{what}: '{mod_name}' has no attribute '{attr}'", "check the name after the ':'")
    if not callable(obj):
        raise PropError(f"{what}: '{attr}' is not callable", ARCH_FORMAT)
    return obj


def import_code(mod_name: str, what: str, fix: str | None = None):
    """The user's module: a ``.py`` path loaded from that file, else a module name imported from the
    folder prop runs in, PYTHONPATH or an installed package. Every failure is one PropError."""
    if mod_name.endswith(".py"):
        return _import_file(what, mod_name, fix)
    return _import_module(what, mod_name, fix)


def code_attribute(module, attr: str):
    """``module.attr.path``, or None if some part of the path is missing."""
    obj = module
    for part in attr.split("."):
        if not part.isidentifier() or not hasattr(obj, part):
            return None
        obj = getattr(obj, part)
    return obj


def _import_module(what: str, mod_name: str, fix: str | None):
    # A model file next to where the user runs prop should just work, as with `python -m`.
    cwd = os.getcwd()
    if cwd not in sys.path:
        sys.path.insert(0, cwd)
    try:
        return importlib.import_module(mod_name)
    except Exception as e:  # ImportError, or any error raised while the user's module runs
        raise PropError(
            f"{what}: cannot import '{mod_name}' ({type(e).__name__}: {e}); it must be importable "
            f"from the folder prop runs in ({cwd}), PYTHONPATH or an installed package",
            fix or "run prop from the folder holding the module, add its folder to PYTHONPATH, or install it",
        ) from None


def _import_file(what: str, file_name: str, fix: str | None):
    path = Path(file_name)
    if not path.is_file():
        raise PropError(
            f"{what}: {path} does not exist (relative to the folder prop runs in, {os.getcwd()})",
            fix or "run prop from the folder the path is relative to, or give the file's path from here",
        )
    import importlib.util

    # A name of its own per file, so two files called model.py do not replace each other.
    name = f"prop_arch_{abs(hash(str(path.resolve())))}"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except Exception as e:  # any error raised while the user's file runs
        del sys.modules[name]
        raise PropError(f"{what}: running {path} failed ({type(e).__name__}: {e})", "fix the file") from None
    return module


def recorded_arch(spec: dict, source: str, arch: str | None) -> tuple[str, str, str | None]:
    """(the factory to call, how errors name it, the fix when it is not found): the user's ``--arch`` of
    this command if given, else the one the bundle at ``source`` records. A bundle records --arch as
    given to personalize, so from another folder the user names their code again."""
    if arch is not None:
        return arch, f"--arch '{arch}'", None
    recorded = spec["arch"]
    where = "the file's path" if recorded.rpartition(":")[0].endswith(".py") else "the module"
    fix = (
        f"pass --arch naming {where} from here (path/to/file.py:factory or package.module:factory; your "
        "own code needs no --trust-remote-code), or run prop from the folder the bundle was made in"
    )
    return recorded, f"bundle {source}: model.arch '{recorded}'", fix


def make_module(
    arch: str, arch_kwargs: dict | None, what: str | None = None, fix: str | None = None,
    fits: dict[str, torch.Tensor] | None = None, source: str = "",
) -> nn.Module:  # fmt: skip
    """``factory(**arch_kwargs)``, checked; ``what`` and ``fix`` as ``resolve_factory`` takes them.
    ``fits``: the weights the module must hold, checked first on a meta-device build (``fitted``)."""
    what = what or f"--arch '{arch}'"
    kwargs = dict(arch_kwargs or {})
    try:
        json.dumps(kwargs)
    except (TypeError, ValueError) as e:
        raise PropError(f"--arch-kwargs is not JSON-serialisable ({e})", "pass a JSON object") from None
    factory = resolve_factory(arch, what=what, fix=fix)

    def make() -> object:
        try:
            return factory(**kwargs)
        except Exception as e:
            raise PropError(
                f"{what}: calling it with --arch-kwargs {json.dumps(kwargs)} failed "
                f"({type(e).__name__}: {e})",
                "check the keyword arguments the factory expects",
            ) from None

    module = make() if fits is None else fitted(make, fits, source, what, FIT_FIX)
    if not isinstance(module, nn.Module):
        raise PropError(
            f"{what} returned a {type(module).__name__}, not a torch.nn.Module",
            "point --arch at a class or a function that returns the model",
        )
    return module


FIT_FIX = "check --arch and --arch-kwargs match the model that saved the checkpoint"


def fitted(
    make: Callable[[], object], weights: dict[str, torch.Tensor], source: str, what: str, fix: str
) -> object:
    """``make()``, called first on the meta device (shapes only: kwargs or a config that claim a huge
    model allocate nothing) and refused in one line unless that module's state dict has exactly the
    weights' names and shapes; then called for real. The factory runs twice. One that cannot build on
    the meta device is built for real and checked after, by ``load_strict``."""
    try:
        with torch.device("meta"):
            probe = make()
    except Exception:  # noqa: BLE001 - the user's factory, whatever it raises there
        probe = None
    if isinstance(probe, nn.Module):
        _check_fit(probe.state_dict(), weights, source, what, fix)
    module = make()
    if isinstance(module, nn.Module) and any(t.is_meta for t in module.state_dict().values()):
        raise PropError(
            f"{what} returned a module whose tensors are on the meta device (does it cache the module it "
            "builds?)",
            "build a new module on every call",
        )
    return module


def _check_fit(own: dict[str, torch.Tensor], weights: dict[str, torch.Tensor], source: str, what: str,
               fix: str) -> None:  # fmt: skip
    """Missing and unexpected keys and shape mismatches between a module's state dict and ``weights``."""
    missing, unexpected = sorted(set(own) - set(weights)), sorted(set(weights) - set(own))
    wrong = [
        f"{k} {tuple(weights[k].shape)} vs {tuple(v.shape)}"
        for k, v in own.items()
        if k in weights and weights[k].shape != v.shape
    ]
    if missing or unexpected or wrong:
        parts = [f"missing keys: {_few(missing)}"] * bool(missing)
        parts += [f"unexpected keys: {_few(unexpected)}"] * bool(unexpected)
        parts += [f"shape mismatch (checkpoint vs model): {_few(wrong)}"] * bool(wrong)
        raise PropError(f"{source} does not fit {what}: " + "; ".join(parts), fix)


def _few(names: list[str]) -> str:
    shown = ", ".join(names[:5])
    return shown + (f", ... ({len(names)} in all)" if len(names) > 5 else f" ({len(names)})")


def load_strict(
    module: nn.Module, weights: dict[str, torch.Tensor], spec: dict, source: str, what: str, fix: str
) -> LoadedModel:
    """Load ``weights`` into a user-built module, listing missing/unexpected keys and shape mismatches.

    Shared by every adapter whose module comes from user code (``--arch``, model folders).
    """
    _check_fit(module.state_dict(), weights, source, what, fix)
    module.load_state_dict(weights, strict=True)
    shape = getattr(module, "input_shape", None)
    try:
        input_shape = tuple(int(d) for d in shape) if shape is not None else None
    except (TypeError, ValueError):
        input_shape = None
    return LoadedModel(
        module=finish(module),
        spec=spec,
        dtypes={k: v.dtype for k, v in weights.items()},
        input_shape=input_shape,
        source=source,
    )


def build(
    spec: dict, weights: dict[str, torch.Tensor], source: str, arch: str | None = None,
    what: str | None = None, fix: str | None = None,
) -> LoadedModel:  # fmt: skip
    """The module ``arch`` (default: ``spec["arch"]``) builds, with ``weights``; the spec stays as given."""
    arch = arch or spec["arch"]
    what = what or f"--arch '{arch}'"
    module = make_module(arch, spec.get("arch_kwargs"), what, fix, fits=weights, source=source)
    return load_strict(module, weights, spec, source, what=what, fix=FIT_FIX)


class ModuleAdapter(Adapter):
    name = "module"
    summary = (
        "a state dict of your own module: .safetensors or .pt/.pth/.bin with "
        "--arch package.module:factory or file.py:factory [--arch-kwargs JSON]"
    )
    options = ("arch", "arch_kwargs")
    manifest_fields = {"arch": text(), "arch_kwargs": RECORD}

    def recognise(self, path: Path, options: CheckpointOptions) -> bool:
        return options.arch is not None and is_weights_file(path)

    def load(self, path: Path, options: CheckpointOptions) -> LoadedModel:
        tensors, _ = read_weights(path)
        spec = {"adapter": self.name, "arch": options.arch, "arch_kwargs": dict(options.arch_kwargs or {})}
        return build(spec, tensors, str(path))

    def rebuild(
        self, spec: dict, weights: dict[str, torch.Tensor], source: str, arch: str | None = None
    ) -> LoadedModel:
        """``arch``: the user's --arch of this command instead of the recorded model.arch."""
        return build(spec, weights, source, *recorded_arch(spec, source, arch))

    def remote_code(self, spec: dict, source: str) -> list[str]:
        # A bundle's model.arch was written by whoever wrote the bundle: --arch on personalize was the
        # user's consent for that command only (--arch on a later command is consent for that one).
        return [f"model.arch {spec.get('arch')!r} (called with model.arch_kwargs; or give yours with --arch)"]
