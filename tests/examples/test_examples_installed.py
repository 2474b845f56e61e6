"""The examples install with prop (pyproject.toml's packages): their tasks and the tests' tiny models
import from the user's own folder, without PYTHONPATH (issue 41, the newcomer list)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
# What the README and docs/formats.md ("The examples as a library") name.
MODULES = ("examples", "examples.il_task", "examples.pi_tiny", "examples.smolvla_tiny",
           "examples.lerobot_reach_task", "examples.reproduce")  # fmt: skip


def test_the_examples_import_from_another_folder(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    code = "import importlib, sys\nfor m in sys.argv[1:]:\n    print(importlib.import_module(m).__file__)"
    r = subprocess.run([sys.executable, "-c", code, *MODULES], cwd=tmp_path, env=env, capture_output=True,
                       text=True, timeout=120)  # fmt: skip
    assert r.returncode == 0, r.stderr
    files = [Path(line) for line in r.stdout.splitlines()]
    assert files[0] == ROOT / "examples" / "__init__.py"  # this checkout's, as pip install -e . makes it
    assert all(f.is_relative_to(ROOT / "examples") for f in files)
