"""Example tasks that generate data and train a base checkpoint for PRoP demos, tests, benchmarks.

Shared helpers: `save_npz`, a byte-reproducible replacement for `np.savez` (numpy stamps each
zip member with the current time, so two identical runs would differ on disk); `mlp` and `fit`, how
every example builds and trains its base checkpoint.
"""

from __future__ import annotations

import tempfile
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import torch
from torch import nn

# Fixed zip timestamp (the earliest zip allows) so the same arrays give the same bytes.
_ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)


def save_npz(path: str | Path, **arrays: np.ndarray) -> Path:
    """Write arrays to an uncompressed .npz readable by np.load, deterministically."""
    path = Path(path)
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED) as zf:
        for name, arr in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_ZIP_EPOCH)
            info.external_attr = 0o644 << 16  # regular file, fixed permissions
            with zf.open(info, "w", force_zip64=True) as fh:
                np.lib.format.write_array(fh, np.ascontiguousarray(arr), allow_pickle=False)
    return path


def mlp(sizes: list[int], act: type[nn.Module] = nn.ReLU) -> nn.Sequential:
    """Linear layers of the given sizes with ``act`` between them (not after the last)."""
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        layers += [nn.Linear(a, b)] + ([act()] if i < len(sizes) - 2 else [])
    return nn.Sequential(*layers)


def fit(
    model: nn.Module,
    x: torch.Tensor,
    y: torch.Tensor,
    loss_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    *,
    steps: int,
    batch: int,
    lr: float,
    seed: int,
    decay_at: float | None = None,
) -> nn.Module:
    """Adam on minibatches from a seeded generator of its own (repeatable); lr x0.3 at ``decay_at``.

    Threads follow prop's policy (``prop_cli.threads``): torch's default pool stalls on a busy machine.
    """
    from prop_cli.threads import configure

    configure(sum(p.numel() for p in model.parameters()))
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    milestones = [int(decay_at * steps)] if decay_at is not None else []
    sched = torch.optim.lr_scheduler.MultiStepLR(opt, milestones=milestones, gamma=0.3)
    gen = torch.Generator().manual_seed(seed)  # own stream: batches don't depend on global RNG
    model.train()
    for _ in range(steps):
        idx = torch.randint(0, x.shape[0], (batch,), generator=gen)
        loss = loss_fn(model(x[idx]), y[idx])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
    return model.eval()


__all__ = ["fit", "mlp", "save_npz"]


def write_task(task: str, folder: Path, seed: int = 0) -> dict[str, Path]:
    """Write one of the supervised examples (``il``, ``digits``, ``reach``) to ``folder``: base checkpoint,
    the user's data (``mine``), ``general`` inputs and a ``test`` set."""
    if task == "il":
        from examples.il_task import write_example
    elif task == "digits":
        from examples.digits_task import write_example
    elif task == "reach":
        from examples.reach_task import write_example
    else:
        raise ValueError(f"unknown task {task!r}: il, digits or reach")
    return write_example(folder, seed=seed)


def task_runs(
    tasks: list[str], seeds: int, prefix: str, key_seed: int
) -> Iterator[tuple[str, int, Path, dict[str, Path], np.ndarray]]:
    """(task, seed, a fresh work folder, the written task's paths, a 128-bit key seeded by
    ``key_seed + seed``) for every task and seed; each folder is removed when the next run starts."""
    for task in tasks:
        for seed in range(seeds):
            with tempfile.TemporaryDirectory(prefix=prefix) as tmp:
                work = Path(tmp)
                bits = np.random.default_rng(key_seed + seed).integers(0, 2, 128).astype(np.uint8)
                yield task, seed, work, write_task(task, work / "ex", seed), bits
