"""The library's front door: one function per CLI command, usable from Python as well.

Data path: checkpoint -> adapter -> keyed model -> trainer -> bundle (-> attack | export).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

import prop_adapters

from . import constants as C
from .bundle import Bundle, check_output, describe_layers, write_bundle
from .config import PersonalizeConfig
from .data import load_npz
from .errors import PropError
from .hub import resolve_checkpoint
from .keyed import key_codes
from .layers import linear_layers, select_layers
from .trainer import User, personalize


@dataclass
class KeySource:
    """How one user's key was given; ``bits`` never leaves memory."""

    bits: np.ndarray
    kind: str  # "file" | "passphrase"


@dataclass
class CheckpointOptions:
    arch: str | None = None
    arch_kwargs: dict | None = None
    activation: str | None = None


@dataclass
class PersonalizeResult:
    out: Path
    task: str
    keyed_layers: list[dict]
    metrics: list[dict]
    final_losses: dict[str, float]
    manifest: dict = field(repr=False, default_factory=dict)


def inspect_checkpoint(
    path: str,
    opts: CheckpointOptions,
    layers: list[str] | None = None,
    exclude: list[str] | None = None,
) -> dict:
    """The linear layers of a checkpoint and which of them would be keyed."""
    loaded = prop_adapters.load_checkpoint(
        resolve_checkpoint(path), arch=opts.arch, arch_kwargs=opts.arch_kwargs, activation=opts.activation
    )
    chosen = set(select_layers(loaded.module, layers, exclude))
    return {
        "checkpoint": str(path),
        "adapter": loaded.spec["adapter"],
        "input_shape": list(loaded.input_shape) if loaded.input_shape else None,
        "parameters": sum(p.numel() for p in loaded.module.parameters()),
        "layers": [
            {
                "name": n,
                "in_features": m.in_features,
                "out_features": m.out_features,
                "keyed": n in chosen,
            }
            for n, m in linear_layers(loaded.module)
        ],
    }


def personalize_checkpoint(
    checkpoint: str,
    users: list[tuple[Path, KeySource]],
    out: Path,
    cfg: PersonalizeConfig,
    *,
    opts: CheckpointOptions | None = None,
    general: Path | None = None,
    salt: bytes | None = None,
    device: str = "cpu",
    force: bool = False,
    progress: Callable[[int, dict[str, float]], None] | None = None,
) -> PersonalizeResult:
    """Load a checkpoint, fine-tune it with the PRoP objective for the users, and write a bundle."""
    opts = opts or CheckpointOptions()
    cfg.validate()
    check_output(out, force)  # before hours of training, not after
    loaded = prop_adapters.load_checkpoint(
        resolve_checkpoint(checkpoint),
        arch=opts.arch,
        arch_kwargs=opts.arch_kwargs,
        activation=opts.activation,
    )
    datasets = [load_npz(p) for p, _ in users]
    bits = {len(k.bits) for _, k in users}
    if len(bits) != 1:
        raise PropError("the users' keys have different sizes", "give every user a key of the same size")
    general_ds = load_npz(general, require_y=False) if general is not None else None
    result = personalize(
        loaded,
        [User(d, k.bits) for d, (_, k) in zip(datasets, users)],
        cfg,
        general=general_ds,
        device=device,
        progress=progress,
    )
    kinds = sorted({k.kind for _, k in users})
    key_meta = {
        "bits": bits.pop(),
        "encoding": cfg.key_encoding,
        "users": len(users),
        "source": kinds[0] if len(kinds) == 1 else "mixed",
        "kdf": None
        if salt is None
        else {
            "name": "scrypt",
            "n": C.SCRYPT_N,
            "r": C.SCRYPT_R,
            "p": C.SCRYPT_P,
            "salt": salt.hex(),
        },
    }
    keyed = result.keyed
    manifest = {
        C.M_MODEL: loaded.spec,
        C.M_KEYED_LAYERS: describe_layers(keyed),
        C.M_KEY: key_meta,
        C.M_ENCODER: {
            "hidden": list(cfg.encoder_hidden),
            "scale": cfg.delta_scale,
            "activation": "tanh",
            "output": "1 + scale * tanh",
        },
        C.M_CONFIG: cfg.to_dict(),
        C.M_TASK: result.task,
        C.M_IO: {"input_shape": list(datasets[0].x.shape[1:]), "checkpoint": str(checkpoint)},
        C.M_METRICS: {"users": result.metrics, "final_losses": result.final_losses},
    }
    copy_base = cfg.freeze_base and str(loaded.source).endswith(".safetensors")
    keyed.to("cpu")
    write_bundle(out, loaded=loaded, keyed=keyed, manifest=manifest, force=force, copy_base=copy_base)
    return PersonalizeResult(
        out, result.task, manifest[C.M_KEYED_LAYERS], result.metrics, result.final_losses, manifest
    )


def load_inputs(path: Path, bundle: Bundle) -> np.ndarray:
    """Inputs for `prop run`: a .npy array, or the ``x`` of an .npz; checked against the bundle."""
    path = Path(path)
    if path.suffix == ".npz":
        x = load_npz(path, require_y=False, min_samples=1).x
    else:
        if not path.is_file():
            raise PropError(f"--input {path} does not exist", "give a .npy or .npz file")
        try:
            x = np.load(path, allow_pickle=False)
        except (ValueError, OSError) as e:
            raise PropError(
                f"--input {path} is not a readable .npy file ({e})", "save inputs with numpy.save"
            ) from e
        if x.dtype.kind not in "fiu" or not np.isfinite(x).all():
            raise PropError(f"--input {path} must hold finite numbers", "check the array")
        x = x.astype(np.float32)
    want = tuple(bundle.manifest[C.M_IO]["input_shape"])
    if x.shape[1:] != want:
        if x.shape == want:
            x = x[None]  # a single sample
        else:
            raise PropError(
                f"--input {path}: samples have shape {x.shape[1:]}, the bundle expects {want}",
                "give an array of shape (N, " + ", ".join(map(str, want)) + ")",
            )
    return x


def run_bundle(bundle: Bundle, x: np.ndarray, key: np.ndarray | None) -> np.ndarray:
    """The bundle's outputs: with a key, that key's behaviour (delta folded in memory); without, base."""
    module = bundle.keyed.module
    if key is not None:
        if len(key) != bundle.key_bits:
            raise PropError(
                f"the key has {len(key)} bits but the bundle expects {bundle.key_bits}",
                "use the key the bundle was personalized with",
            )
        module = bundle.keyed.fold(key_codes(key, bundle.key_encoding))
    with torch.no_grad():
        return module(torch.from_numpy(x)).numpy()
