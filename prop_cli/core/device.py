"""Which device torch computes on: ``--device auto|cpu|cuda[:N]``."""

from __future__ import annotations

import torch

from prop_cli.errors import PropError


def resolve_device(name: str) -> torch.device:
    """``auto`` is CUDA when there is one, else the CPU; anything else must exist here."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except RuntimeError as e:
        raise PropError(f"--device {name!r} is not a device", "use auto, cpu or cuda[:N]") from e
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise PropError(
            f"--device {name} asked for CUDA, which is not available here",
            "use --device cpu or auto",
        )
    return dev
