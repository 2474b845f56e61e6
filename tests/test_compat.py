"""The import paths of prop 0.1 still work for one release, each with a DeprecationWarning naming the new
path (prop_cli/compat.py); patching a registry through an old path patches the one prop uses."""

from __future__ import annotations

import subprocess
import sys

from prop_cli import compat


def _run(code: str) -> str:
    out = subprocess.run(
        [sys.executable, "-W", "always::DeprecationWarning", "-c", code], capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr
    return out.stdout + out.stderr


def test_every_old_path_imports_and_warns():
    code = (
        "import importlib, warnings\n"
        f"for old in {sorted(compat.MOVED)!r}:\n"
        "    with warnings.catch_warnings(record=True) as seen:\n"
        "        warnings.simplefilter('always')\n"
        "        m = importlib.import_module(old)\n"
        "    ok = any(issubclass(w.category, DeprecationWarning) and f'{old} moved to' in str(w.message)\n"
        "             for w in seen)\n"
        "    print(old, ok and bool(dir(m)))\n"
    )
    lines = _run(code).split("\n")
    for old in compat.MOVED:
        assert f"{old} True" in lines, old


def test_old_names_are_the_new_objects_and_registries_patch_through():
    text = _run(
        "import prop_adapters, prop_cli.adapters as new\n"
        "from prop_adapters.base import Adapter\n"
        "from prop_cli.adapters.base import Adapter as A2\n"
        "from prop_cli.trainer import personalize, FallbackPool\n"
        "import prop_cli.probes as old_probes, prop_cli.attack.probes as probes\n"
        "old_probes.PROBES = old_probes.PROBES[:1]\n"
        "print(prop_adapters.ADAPTERS is new.ADAPTERS, Adapter is A2, callable(personalize),\n"
        "      FallbackPool.__module__, len(probes.PROBES))\n"
    )
    assert "True True True prop_cli.train.array 1" in text


def test_new_paths_import_without_warnings():
    out = subprocess.run(
        [sys.executable, "-W", "error::DeprecationWarning", "-c",
         "import prop_cli.api, prop_cli.cli.main, prop_cli.adapters, prop_cli.attack.probes.base"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
