"""Users' data as array recipes train on it: checked against the model, one task, tensors."""

from __future__ import annotations

import torch

from prop_adapters import LoadedModel
from prop_cli.datasources import Dataset
from prop_cli.errors import PropError
from prop_cli.fit import output_width, prepare

# Inputs per forward when caching a module's outputs. 1024 rows keep a small model's activations in
# the core's cache: the IL MLP labels 8192 noisy fallback inputs (FallbackPool's bank) in 8.2 ms in
# chunks of 1024 against 15.0 ms in one forward of 8192 (docs/speed.md, "The small-model step").
_CHUNK = 1024


@torch.no_grad()
def outputs(module: torch.nn.Module, x: torch.Tensor) -> torch.Tensor:
    """The module's outputs on many inputs, in chunks, in fp32 even inside a bf16 step: these are the
    original's outputs the fallback is distilled towards, and they should be the original's exactly."""
    with torch.autocast(x.device.type, enabled=False):
        return torch.cat([module(x[i : i + _CHUNK]) for i in range(0, len(x), _CHUNK)])


def targets_tensor(ds: Dataset, task: str) -> torch.Tensor:
    """y as the loss wants it: labels (N,), or float targets (N, d)."""
    y = torch.from_numpy(ds.y)
    return y if task == "classification" or y.dim() > 1 else y[:, None]


def prepare_users(
    loaded: LoadedModel, datasets: list[Dataset], general: Dataset | None, task: str | None
) -> tuple[list[Dataset], str]:
    """Users' data checked against the model, with one task for all; general inputs checked too."""
    prepared = [prepare(loaded, d, "--data", task) for d in datasets]
    tasks = {t for _, t in prepared}
    if len(tasks) != 1:
        raise PropError(
            "the --data files hold different kinds of y (class labels and float targets)",
            "give every user the same kind of y, or set --task",
        )
    if general is not None:
        output_width(loaded, general, "--general-data")
    return [d for d, _ in prepared], tasks.pop()
