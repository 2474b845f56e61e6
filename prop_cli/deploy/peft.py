"""`prop export BUNDLE --peft DIR --key-file K`: a sealed user's payload, opened with their key, as a
standard peft LoRA adapter folder (``adapter_config.json`` + ``adapter_model.safetensors``).

Only ``peft-lora`` payloads export: ``W + B A`` is exactly peft's LoRA with ``lora_alpha = r`` (scaling
1). For a convolution, ``A`` (r, in * kernel) becomes peft's ``lora_A`` convolution weight (r, in,
*kernel) and ``B`` (out, r) its 1x1 ``lora_B`` (out, r, 1, ...): peft merges them as ``B @ A`` over the
flattened kernel, as the payload does. ``lora`` payloads scale each input channel too (a full-rank
change no LoRA holds) and are refused, like ``delta`` and ``full``.

The adapter's ``base_model_name_or_path`` is the bundle's base: its ``lerobot/`` folder for a LeRobot
policy (so LeRobot's ``use_peft`` path loads the policy and then the adapter), the bundle folder
otherwise. The adapter is the user's behaviour in the clear: it is written only with their key, never
into the bundle, and never over an existing folder without ``force``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from prop_cli import constants as C
from prop_cli.bundle import Bundle
from prop_cli.errors import PropError
from prop_cli.files import dump_json, staged_dir

# Only a peft-lora payload is a peft adapter, and that is chosen before training (bundle.modes says it too).
PEFT_FIX = "personalize again with --seal --payload peft-lora, the one payload export --peft takes"
PEFT_PREFIX = "base_model.model."  # peft's saved state-dict names: the wrapped model's module paths


@dataclass
class PeftExport:
    out: Path
    layers: int
    rank: int
    base: str


def adapter_tensors(payload) -> dict[str, torch.Tensor]:
    """The payload's tensors under peft's names and shapes (``lora_A`` / ``lora_B`` per keyed layer)."""
    spec = payload.spec
    out = {}
    for layer in spec.layers:
        name, kernel = layer["name"], [int(k) for k in layer.get("kernel", ())]
        a, b = payload.tensor(name, "lora_a").detach(), payload.tensor(name, "lora_b").detach()
        if kernel:
            if int(layer.get("groups", 1)) != 1:
                raise PropError(
                    f"--peft: {name} is a grouped convolution, which peft's LoRA does not take",
                    "leave grouped convolutions out of --layers",
                )
            a = a.reshape(spec.rank, int(layer["in_features"]), *kernel)
            b = b.reshape(int(layer["out_features"]), spec.rank, *[1] * len(kernel))
        out[f"{PEFT_PREFIX}{name}.lora_A.weight"] = a.contiguous().float()
        out[f"{PEFT_PREFIX}{name}.lora_B.weight"] = b.contiguous().float()
    return out


def adapter_config(payload, base: str) -> dict:
    """peft's LoraConfig for the payload: its rank, lora_alpha = r, exactly its keyed layers."""
    names = [layer["name"] for layer in payload.spec.layers]
    return {
        "peft_type": "LORA",
        "task_type": None,
        "base_model_name_or_path": base,
        "r": payload.spec.rank,
        "lora_alpha": payload.spec.rank,  # scaling lora_alpha / r = 1: the payload's W + B A
        "lora_dropout": 0.0,
        "bias": "none",
        "fan_in_fan_out": False,
        "inference_mode": True,
        # A regex peft matches against whole module names: exactly the keyed layers (a plain list would
        # also match any module whose name ends in one of them).
        "target_modules": "(" + "|".join(re.escape(n) for n in names) + ")",
    }


def export_peft(bundle: Bundle, bits: np.ndarray, out: Path) -> PeftExport:
    """Write the adapter ``bits`` opens in ``bundle`` to the new folder ``out`` (checked by the caller)."""
    from safetensors.torch import save_file

    payload = bundle.mode.payload_for(bits)  # an unsealed bundle's mode refuses, naming PEFT_FIX
    if payload is None:
        raise PropError(
            f"--peft: the key opens no record of {bundle.path}", "pass the key this bundle was sealed for"
        )
    if not payload.spec.variant.peft_lora:
        raise PropError(
            f"--peft: {bundle.path} holds {payload.spec.kind} payloads, which no peft LoRA adapter can hold",
            PEFT_FIX,
        )
    lerobot = bundle.path / C.LEROBOT_DIR
    base = str((lerobot if lerobot.is_dir() else bundle.path).resolve())
    tensors = adapter_tensors(payload)
    with staged_dir(out, what="adapter folder") as tmp:
        save_file(tensors, str(tmp / C.PEFT_WEIGHTS), metadata={"format": "pt"})
        (tmp / C.PEFT_CONFIG).write_text(dump_json(adapter_config(payload, base)))
    return PeftExport(Path(out), len(payload.spec.layers), payload.spec.rank, base)
