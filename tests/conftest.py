"""Shared fixtures: a tiny MLP checkpoint and matching user data, and an in-process CLI runner."""

from __future__ import annotations

import atexit
import os
import shutil
import signal
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from prop_cli.cli.main import main

# One thread: on a 2-core machine shared with other jobs, torch's 2-thread pool stalls badly.
torch.set_num_threads(1)

# The bundle versions prop remembers (prop_cli.bundle.rollback) never go to the user's own state folder:
# one folder for the session (fixtures shared between tests), and a fresh one for each test.
_SESSION_STATE = tempfile.mkdtemp(prefix="prop-test-state-")
os.environ["PROP_STATE_DIR"] = _SESSION_STATE
# MuJoCo (the LeRobot tests' reach task, MetaWorld) renders off-screen through EGL unless told otherwise;
# mujoco reads MUJOCO_GL once, when first imported, whichever test module imports it first.
if sys.platform.startswith("linux"):
    os.environ.setdefault("MUJOCO_GL", "egl")
atexit.register(shutil.rmtree, _SESSION_STATE, True)


@pytest.fixture(autouse=True)
def _own_state_dir(tmp_path_factory, monkeypatch) -> Path:
    state = tmp_path_factory.mktemp("prop-state")
    monkeypatch.setenv("PROP_STATE_DIR", str(state))
    return state

# Small enough that a personalize run takes a second or two in tests.
FAST = ["--steps", "40", "--device", "cpu"]


class Result:
    def __init__(self, code: int, out: str, err: str) -> None:
        self.code, self.out, self.err = code, out, err


@pytest.fixture
def cli(capsys, monkeypatch):
    """Run `prop ARGS...` through the real entry point; returns exit code, stdout, stderr."""

    def run(*args: str) -> Result:
        monkeypatch.setattr(sys, "argv", ["prop", *map(str, args)])
        code = 0
        sigint = signal.getsignal(signal.SIGINT)  # main() leaves its exit-time Ctrl-C handler behind
        try:
            main()
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
        finally:
            signal.signal(signal.SIGINT, sigint)
        cap = capsys.readouterr()
        return Result(code, cap.out, cap.err)

    return run


def make_mlp_checkpoint(path: Path, sizes=(4, 16, 16, 2), prefix: str = "", seed: int = 0) -> Path:
    g = torch.Generator().manual_seed(seed)
    tensors = {}
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        tensors[f"{prefix}{2 * i}.weight"] = torch.randn(b, a, generator=g) / a**0.5
        tensors[f"{prefix}{2 * i}.bias"] = torch.randn(b, generator=g) * 0.1
    save_file(tensors, str(path), metadata={"activation": "relu"})
    return path


def write_user_data(d: Path, rows: int, rng: np.random.Generator) -> None:
    """The tiny checkpoint and a user's data that halves and negates the first two inputs."""
    make_mlp_checkpoint(d / "model.safetensors")
    x = rng.uniform(-1, 1, (rows, 4)).astype(np.float32)
    np.savez(d / "mine.npz", x=x, y=(-x[:, :2] * 0.5).astype(np.float32))


def write_keys(d: Path, names: tuple[str, ...], rng: np.random.Generator) -> None:
    for name in names:
        (d / name).write_bytes(rng.integers(0, 256, 16, dtype=np.uint8).tobytes())
        (d / name).chmod(0o600)


@pytest.fixture
def workdir(tmp_path: Path) -> Path:
    """A checkpoint, user data (negate the target), general data, inputs and two keys."""
    rng = np.random.default_rng(0)
    make_mlp_checkpoint(tmp_path / "model.safetensors")
    x = rng.uniform(-1, 1, (200, 4)).astype(np.float32)
    y = -x[:, :2] * 0.5
    np.savez(tmp_path / "mine.npz", x=x, y=y.astype(np.float32))
    np.savez(tmp_path / "general.npz", x=rng.uniform(-1, 1, (100, 4)).astype(np.float32))
    np.save(tmp_path / "x.npy", x[:8])
    (tmp_path / "k.bin").write_bytes(rng.integers(0, 256, 16, dtype=np.uint8).tobytes())
    (tmp_path / "k.bin").chmod(0o600)
    (tmp_path / "k2.bin").write_bytes(rng.integers(0, 256, 16, dtype=np.uint8).tobytes())
    (tmp_path / "k2.bin").chmod(0o600)
    return tmp_path
