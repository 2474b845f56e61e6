"""Import paths of prop 0.1.0 that moved in the layout of 0.2 (docs/design.md maps the new one).

Each old module path still imports, for one release, as an alias of the module(s) that now hold its
names; importing it warns (``DeprecationWarning``) with the new path. Attributes read or set through
the old path are those of the new modules, so registries patched through it (``PROBES``, ``ADAPTERS``)
are the ones prop uses.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import types
import warnings

# old module -> the modules its public names live in now (first match wins)
MOVED: dict[str, tuple[str, ...]] = {
    "prop_cli.audit": ("prop_cli.attack.audit", "prop_cli.attack.target"),
    "prop_cli.audit_report": ("prop_cli.attack.report",),
    "prop_cli.batch_axes": ("prop_cli.core.batch_axes",),
    "prop_cli.cli.keygen": ("prop_cli.cli.keygen_cmd",),
    "prop_cli.data": ("prop_cli.datasources.fit",),
    "prop_cli.evaluate": ("prop_cli.train.report", "prop_cli.core.keyed_model"),
    "prop_cli.export": (
        "prop_cli.deploy.onnx", "prop_cli.deploy.onnx.unsealed", "prop_cli.deploy.onnx.common",
    ),
    "prop_cli.hardening": ("prop_cli.train.hardening",),
    "prop_cli.hub": ("prop_cli.adapters.hub",),
    "prop_cli.keyed": ("prop_cli.core.keyed_model",),
    "prop_cli.keys": ("prop_cli.core.key_files",),
    "prop_cli.keyspace": ("prop_cli.core.key_sampling",),
    "prop_cli.layers": ("prop_cli.core.layers",),
    "prop_cli.manifest": ("prop_cli.bundle.manifest",),
    "prop_cli.metrics": ("prop_cli.core.metrics",),
    "prop_cli.objective": ("prop_cli.train.objective",),
    "prop_cli.onnx_runtime": ("prop_cli.deploy.onnx", "prop_cli.deploy.onnx.common"),
    "prop_cli.optim": ("prop_cli.train.optim",),
    "prop_cli.payload": ("prop_cli.core.payload",),
    "prop_cli.policy": ("prop_cli.bundle.runtime",),
    "prop_cli.policy_trainer": ("prop_cli.train.policy", "prop_cli.train.sealed_policy"),
    "prop_cli.policy_view": (
        "prop_cli.adapters.lerobot.flat", "prop_cli.datasources.fit", "prop_cli.bundle.runtime",
        "prop_cli.attack.target",
    ),
    "prop_cli.probes": ("prop_cli.attack.probes",),
    "prop_cli.publish": ("prop_cli.deploy.publish",),
    "prop_cli.rollout": ("prop_cli.deploy.rollout",),
    "prop_cli.seal": ("prop_cli.bundle.cipher",),
    "prop_cli.sealed": ("prop_cli.bundle.records", "prop_cli.train.sealed", "prop_cli.train.sealed_array"),
    "prop_cli.trainer": (
        "prop_cli.train.array", "prop_cli.train.data", "prop_cli.train.recipe", "prop_cli.core.device",
    ),
    "prop_cli.vecnormalize": ("prop_cli.adapters.sb3.vecnormalize",),
    "prop_adapters": ("prop_cli.adapters",),
    "prop_adapters.activations": ("prop_cli.adapters.activations",),
    "prop_adapters.base": ("prop_cli.adapters.base",),
    "prop_adapters.folder": ("prop_cli.adapters.folder",),
    "prop_adapters.lerobot": ("prop_cli.adapters.lerobot", "prop_cli.adapters.lerobot.adapter"),
    "prop_adapters.mlp": ("prop_cli.adapters.mlp",),
    "prop_adapters.module": ("prop_cli.adapters.module",),
    "prop_adapters.sb3": ("prop_cli.adapters.sb3", "prop_cli.adapters.sb3.adapter"),
    "prop_adapters.sb3_zip": ("prop_cli.adapters.sb3.archive",),
    "prop_adapters.weights": ("prop_cli.adapters.weights",),
}
# Old packages whose submodules moved with them.
MOVED_PACKAGES = {"prop_cli.probes": "prop_cli.attack.probes"}


class MovedModule(types.ModuleType):
    """An old module path: reads and writes go to the modules that hold the names now."""

    def __init__(self, name: str, targets: tuple[str, ...]) -> None:
        super().__init__(name)
        object.__setattr__(self, "_targets", [importlib.import_module(t) for t in targets])
        object.__setattr__(self, "__doc__", f"Moved to {', '.join(targets)} (this path goes in prop 0.3).")

    def _owner(self, name: str) -> types.ModuleType | None:
        return next((t for t in self._targets if hasattr(t, name)), None)

    def __getattr__(self, name: str):
        owner = self._owner(name)
        if owner is None:
            raise AttributeError(f"module {self.__name__!r} has no attribute {name!r}")
        return getattr(owner, name)

    def __setattr__(self, name: str, value) -> None:
        if name.startswith("__"):
            object.__setattr__(self, name, value)
            return
        setattr(self._owner(name) or self._targets[0], name, value)

    def __dir__(self) -> list[str]:
        return sorted({n for t in self._targets for n in dir(t)})


def _targets(fullname: str) -> tuple[str, ...] | None:
    if fullname in MOVED:
        return MOVED[fullname]
    for old, new in MOVED_PACKAGES.items():
        if fullname.startswith(old + "."):
            return (new + fullname[len(old) :],)
    return None


class _Loader(importlib.abc.Loader):
    def create_module(self, spec: importlib.machinery.ModuleSpec) -> types.ModuleType:
        return MovedModule(spec.name, _targets(spec.name))

    def exec_module(self, module: types.ModuleType) -> None:
        if _is_package(module.__name__):
            object.__setattr__(module, "__path__", [])  # its old submodules resolve through the finder
        warnings.warn(
            f"{module.__name__} moved to {', '.join(t.__name__ for t in module._targets)}; "
            "the old import path goes in prop 0.3",
            DeprecationWarning,
            stacklevel=2,
        )


def _is_package(fullname: str) -> bool:
    return fullname in MOVED_PACKAGES or any(old.startswith(fullname + ".") for old in MOVED)


class _Finder(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname, path=None, target=None):
        if _targets(fullname) is None:
            return None
        return importlib.machinery.ModuleSpec(fullname, _Loader(), is_package=_is_package(fullname))


def install() -> None:
    if not any(isinstance(f, _Finder) for f in sys.meta_path):
        sys.meta_path.insert(0, _Finder())
