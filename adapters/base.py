"""What every adapter returns, and reading a weights file without unpickling anything."""

from __future__ import annotations

import pickle
import re
from dataclasses import dataclass, field
from pathlib import Path

import torch

from prop_cli.errors import PropError

SAFETENSORS_EXTS = (".safetensors",)
TORCH_EXTS = (".pt", ".pth", ".bin")
# Wrappers that training scripts commonly put around the state dict.
STATE_DICT_ENTRIES = ("state_dict", "model_state_dict")


@dataclass
class LoadedModel:
    """A checkpoint turned into a module whose state-dict names are the checkpoint's names."""

    module: torch.nn.Module  # built, weights loaded, eval mode, float32
    spec: dict  # JSON-serialisable; spec["adapter"] names the adapter; rebuilds the module
    dtypes: dict[str, torch.dtype]  # original dtype of every checkpoint tensor, by name
    input_shape: tuple[int, ...] | None  # per-sample input shape if known, e.g. (4,)
    source: str  # the path it came from
    # Checkpoint tensors the module does not use (e.g. an SB3 critic): written back into the bundle's
    # base file untouched, so the whole original state dict round-trips.
    extra: dict[str, torch.Tensor] = field(default_factory=dict)


def _check_file(path: Path) -> None:
    if not path.exists():
        raise PropError(f"checkpoint {path} does not exist", "check the path")
    if path.is_dir():
        raise PropError(
            f"checkpoint {path} is a directory",
            "pass the weights file itself (.safetensors, .pt, .pth or .bin)",
        )
    if path.stat().st_size == 0:
        raise PropError(f"checkpoint {path} is empty", "re-export the checkpoint")


def _read_safetensors(path: Path) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            metadata = dict(f.metadata() or {})
            tensors = {name: f.get_tensor(name) for name in f.keys()}
    except (SafetensorError, OSError, ValueError, RuntimeError, KeyError) as e:
        raise PropError(
            f"checkpoint {path} is not a readable safetensors file ({e})",
            "re-export it with safetensors.torch.save_file",
        ) from None
    return tensors, metadata


def _corrupt(path: Path, e: Exception) -> PropError:
    return PropError(
        f"checkpoint {path} is corrupt or not a torch file ({type(e).__name__})",
        "re-export it with torch.save(model.state_dict(), path) or as .safetensors",
    )


def _read_torch(path: Path) -> dict[str, torch.Tensor]:
    try:
        obj = torch.load(str(path), weights_only=True, map_location="cpu")
    except pickle.UnpicklingError as e:
        text = str(e)
        if "Weights only load failed" not in text:
            raise _corrupt(path, e) from None
        # weights_only refused an arbitrary object: that is the point, never retry without it.
        m = re.search(r"Unsupported global: GLOBAL (\S+)", text)
        what = f"it pickles {m.group(1)}" if m else "it pickles objects other than tensors"
        raise PropError(
            f"checkpoint {path} was refused: {what}, and prop never unpickles code",
            "save only the state dict: torch.save(model.state_dict(), path), or use .safetensors",
        ) from None
    except Exception as e:  # torch raises many types (KeyError, RuntimeError, EOFError) on junk
        raise _corrupt(path, e) from None
    if isinstance(obj, dict):
        for entry in STATE_DICT_ENTRIES:
            if isinstance(obj.get(entry), dict):
                obj = obj[entry]
                break
    if not isinstance(obj, dict):
        raise PropError(
            f"checkpoint {path} holds a {type(obj).__name__}, not a state dict",
            "save a flat dict name -> tensor: torch.save(model.state_dict(), path)",
        )
    bad = [str(k) for k, v in obj.items() if not isinstance(k, str) or not torch.is_tensor(v)]
    if bad:
        shown = ", ".join(bad[:3]) + (f" (+{len(bad) - 3} more)" if len(bad) > 3 else "")
        raise PropError(
            f"checkpoint {path} is not a flat state dict: entries {shown} are not tensors",
            "save only model.state_dict(), or put it under a 'state_dict' entry",
        )
    return dict(obj)


def read_weights(path: str | Path) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """Tensors by name plus safetensors metadata ({} for torch files). Never unpickles."""
    path = Path(path)
    _check_file(path)
    suffix = path.suffix.lower()
    if suffix in SAFETENSORS_EXTS:
        tensors, metadata = _read_safetensors(path)
    elif suffix in TORCH_EXTS:
        tensors, metadata = _read_torch(path), {}
    else:
        raise PropError(
            f"checkpoint {path} has unsupported extension '{path.suffix}'",
            "use .safetensors, .pt, .pth or .bin",
        )
    if not tensors:
        raise PropError(f"checkpoint {path} contains no tensors", "check that it is the right file")
    return tensors, metadata


def finish(module: torch.nn.Module) -> torch.nn.Module:
    """Common last step of every adapter: float32, eval mode, no autograd surprises."""
    return module.float().eval()
