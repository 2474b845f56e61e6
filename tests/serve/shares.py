"""Helpers of the prop serve tests."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import FAST

# openpi-client 0.1.2 calls websockets' sync connect() outside a `with`, which websockets >= 16 deprecates.
OPENPI_CONNECT = pytest.mark.filterwarnings("ignore:connect\\(\\) must be used:DeprecationWarning")


def personalize_here(wd: Path, out: str = "mine.prop", *extra: str) -> None:
    """prop personalize in a subprocess: a module-scoped fixture cannot use the in-process `cli` one."""
    args = ["personalize", wd / "model.safetensors", "--data", wd / "mine.npz", "--key-file", wd / "k.bin",
            "--out", wd / out, *FAST, *extra]  # fmt: skip
    code = "from prop_cli.cli.main import main; main()"
    done = subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True,
                          timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr
