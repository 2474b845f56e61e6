"""Frozen weights held in bfloat16 under ``--precision bf16`` (every recipe: LeRobot policies, array
models, unsealed and sealed).

Under bf16 autocast (``loop.mixed_precision``) a matrix multiply reads its weight as bf16 whatever it is
held in, so a parameter that does not train loses nothing by being held bf16 while the steps run, and
takes half the memory (a real-size pi0's frozen VLM: 6.5 GB less). The parameters that train, their
gradients and Adam's state stay fp32 (the precision's master weights). After the steps the frozen
weights are put back exactly as the checkpoint holds them, so the report, the bundle and its no-key
outputs see the original's weights bit for bit:

- where the checkpoint itself holds them in bf16 (``LoadedModel.dtypes``), casting back is exact;
- otherwise they are read again from the checkpoint's safetensors file; where that cannot be done (a
  torch file, names that differ from the file's), nothing is cast.

Under ``--precision bf16`` personalize loads a LeRobot policy with each weight in the dtype its checkpoint
stores it in (``CheckpointOptions.keep_dtypes``): a bf16 checkpoint is never held in fp32, not at the
load, not in the report. Its weights that train are made fp32 (``trained_in_fp32``), and what runs the
policy outside the steps (the layer probe, the report) runs under the steps' autocast (``held_autocast``).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from pathlib import Path

import torch

from prop_adapters import LoadedModel
from prop_adapters.folder import WEIGHTS
from prop_adapters.weights import safetensors_shapes, sniff

from .loop import mixed_precision


def trained_in_fp32(module: torch.nn.Module) -> None:
    """``module``'s parameters that train made fp32 where the checkpoint held them in a lower precision
    (``keep_dtypes``): the precision's master weights, as Adam and the gradient clip need them."""
    for p in module.parameters():
        if p.requires_grad and p.is_floating_point() and p.dtype != torch.float32:
            p.data = p.data.float()


def held_autocast(module: torch.nn.Module, device: torch.device | str) -> contextlib.AbstractContextManager:
    """The steps' bf16 autocast where ``module`` holds weights in bf16 (a bf16 checkpoint loaded in its
    dtype), so a forward outside the steps (a probe, the report) computes as they do; else nothing."""
    if any(p.dtype == torch.bfloat16 for p in module.parameters()):
        return mixed_precision("bf16", device)
    return contextlib.nullcontext()


def frozen_in_bf16(
    module: torch.nn.Module, loaded: LoadedModel, matrices_only: bool = False
) -> Callable[[], None] | None:
    """Cast ``module``'s parameters that do not train to bfloat16; return what puts them back as the
    checkpoint ``loaded`` came from holds them (its ``dtypes``; else its file), or None,
    and nothing cast, where that cannot be done exactly. ``matrices_only``: only parameters of two or
    more dimensions (an array model's norms and biases stay as they are: ops that autocast leaves in
    fp32 would otherwise meet a bf16 weight)."""
    frozen = {
        n: p
        for n, p in module.named_parameters()
        if not p.requires_grad and p.is_floating_point() and p.dtype != torch.bfloat16
        and (p.dim() >= 2 or not matrices_only)
    }  # fmt: skip
    if not frozen:
        return None
    dtypes = {n: p.dtype for n, p in frozen.items()}
    if all(loaded.dtypes.get(n) == torch.bfloat16 for n in frozen):
        restore = _cast_back(frozen, dtypes)  # the checkpoint's values are bf16: the cast loses nothing
    else:
        restore = _read_back(frozen, dtypes, str(loaded.source))
        if restore is None:
            return None
    for p in frozen.values():
        p.data = p.data.to(torch.bfloat16)
    return restore


def _cast_back(frozen: dict[str, torch.nn.Parameter], dtypes: dict[str, torch.dtype]) -> Callable[[], None]:
    def restore() -> None:
        for n, p in frozen.items():
            p.data = p.data.to(dtypes[n])

    return restore


def _read_back(
    frozen: dict[str, torch.nn.Parameter], dtypes: dict[str, torch.dtype], source: str
) -> Callable[[], None] | None:
    path = Path(source) / WEIGHTS if Path(source).is_dir() else Path(source)
    if not path.is_file() or sniff(path) != "safetensors" or not set(frozen) <= set(safetensors_shapes(path)):
        return None

    def restore() -> None:
        from safetensors import safe_open

        with safe_open(str(path), framework="pt", device="cpu") as f:
            for n, p in frozen.items():
                p.data = f.get_tensor(n).to(device=p.device, dtype=dtypes[n])

    return restore
