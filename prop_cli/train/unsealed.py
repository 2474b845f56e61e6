"""What the unsealed recipes (``array``, ``policy``) give back: the base with its trained key encoder,
written as an unsealed bundle (the paper's PRoP: base weights and encoder in the clear)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch

from prop_adapters import LoadedModel
from prop_cli import constants as C
from prop_cli.bundle import describe_layers, write_unsealed
from prop_cli.config import UnsealedConfig
from prop_cli.core.keyed_model import KeyedModel

from .recipe import Trained, Written


@dataclass
class Personalized(Trained):
    keyed: KeyedModel
    original: torch.nn.Module
    task: str
    metrics: list[dict]  # one report per user (report.user_report, or a policy's chunk report)
    final_losses: dict[str, float]
    loaded: LoadedModel | None = field(default=None, repr=False)
    cfg: UnsealedConfig | None = field(default=None, repr=False)
    input_shape: list | dict | None = None  # per sample; per feature name for policies
    users: int = 1
    keys: list = field(default_factory=list, repr=False)  # the users' key bits: enrolled, never written

    def write(self, out: Path, manifest: dict, *, force: bool = False) -> Written:
        cfg = self.cfg
        full = {
            **manifest,
            C.M_KEYED_LAYERS: describe_layers(self.keyed),
            C.M_KEY: {**manifest[C.M_KEY], "encoding": cfg.key_encoding, "users": self.users},
            C.M_ENCODER: {
                "hidden": list(cfg.encoder_hidden),
                "scale": cfg.delta_scale,
                "activation": "tanh",
                "output": "1 + scale * tanh",
            },
            C.M_TASK: self.task,
            C.M_IO: {"input_shape": self.input_shape, **manifest[C.M_IO]},
            C.M_METRICS: {"users": self.metrics, "final_losses": self.final_losses},
        }
        copy_base = cfg.freeze_base and str(self.loaded.source).endswith(".safetensors")
        self.keyed.to("cpu")
        written = write_unsealed(
            out, loaded=self.loaded, keyed=self.keyed, manifest=full, keys=self.keys, force=force,
            copy_base=copy_base,
        )  # fmt: skip
        return Written(written, self.metrics, self.final_losses)
