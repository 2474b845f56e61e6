"""The tiny LeRobot bases that the adapter tests (tests/adapters/test_lerobot*.py) and the serve tests
(tests/serve/test_serve_lerobot.py) personalize, built one way for both: the reach task's recorded data
(examples/lerobot_reach_task.py: ``general`` episodes for the base, a ``user``'s shifted ones) and a base
policy trained a few steps on ``general``. Each returns the base's folder under ``d``."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from examples import lerobot_reach_task as task


def reach_data(d: Path, general: int, user: int, *, camera: bool = False) -> None:
    """``d/general`` (``general`` episodes, the task's own goal) and ``d/user`` (``user`` episodes, the goal
    moved by ``task.USER_OFFSET``)."""
    task.record(d / "general", general, 0, np.zeros(3, np.float32), camera=camera)
    task.record(d / "user", user, 50_000, task.USER_OFFSET, camera=camera)


def act_base(d: Path, steps: int = 5) -> Path:
    """A tiny ACT (state only) trained ``steps`` steps on 4 general episodes; 3 user episodes beside it."""
    reach_data(d, 4, 3)
    task.train_base(d / "general", d / "act", steps=steps)
    return d / "act"


def diffusion_base(d: Path, steps: int = 5) -> Path:
    """A tiny Diffusion policy trained ``steps`` steps on 3 general episodes; 2 user episodes beside it."""
    reach_data(d, 3, 2)
    task.train_base(d / "general", d / "diffusion", steps=steps, kind="diffusion")
    return d / "diffusion"


def smolvla_base(d: Path, steps: int = 3) -> Path:
    """A tiny SmolVLA (examples/smolvla_tiny.py: its VLM built in ``d/vlm``, a camera and the state)
    trained ``steps`` steps on 2 general episodes; 2 user episodes beside it."""
    from examples import smolvla_tiny

    reach_data(d, 2, 2, camera=True)
    vlm = smolvla_tiny.build_vlm(d / "vlm")
    built = smolvla_tiny.build_smolvla(vlm, task.dataset_stats(d / "general"))
    task.train_base(d / "general", d / "smolvla", steps=steps, built=built)
    return d / "smolvla"


def originals(folder: Path, data) -> np.ndarray:
    """The checkpoint at ``folder`` as prop loads it, run on every row of ``data``: the actions a bundle's
    no-key output must equal bit for bit."""
    import torch

    from prop_adapters import load_checkpoint

    orig = load_checkpoint(folder).policy
    batch = orig.batches(data, "--data")
    with torch.no_grad():
        return orig.post(orig.chunk({k: batch[k] for k in orig.row_shapes})).numpy()
