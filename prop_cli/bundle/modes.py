"""How a bundle turns a key into behaviour: its mode, chosen here and nowhere else.

- ``Unsealed`` (the paper's PRoP): a key encoder over the base, hooked onto the keyed layers; a key
  becomes one delta per keyed layer (Eq. 5).
- ``Sealed``: the base is the original; a key opens its user's encrypted record, whose payload is
  folded into a copy of the base, or opens nothing and the base runs.

Everything downstream (running, the audit, exports, publishing) asks the mode, not the manifest.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch
from torch import nn

from prop_cli import constants as C
from prop_cli.adapters import LoadedModel, read_weights
from prop_cli.core.keyed_model import KeyedModel, KeyEncoder, key_codes
from prop_cli.errors import PropError

from . import manifest as schema
from .records import SealedState, load_state


class Mode(ABC):
    """What a bundle's mode answers. ``keyed`` is the encoder over the base (unsealed only), ``state``
    the payload layout and encrypted records (sealed only)."""

    name: ClassVar[str]
    keyed: KeyedModel | None = None
    state: SealedState | None = None

    @property
    def sealed(self) -> bool:
        return self.state is not None

    @property
    @abstractmethod
    def layer_names(self) -> list[str]: ...

    @abstractmethod
    def unlock(self, module: nn.Module, bits: np.ndarray) -> nn.Module | None:
        """A copy of ``module`` (the base, or a view with its keyed layers) showing what ``bits`` unlock,
        in memory only; None where the key unlocks nothing (the base then runs)."""

    @abstractmethod
    def opens(self, bits: np.ndarray) -> bool:
        """Whether ``bits`` unlock a behaviour of their own."""

    @abstractmethod
    def on(self, module: nn.Module) -> Mode:
        """The same mode over ``module``, a view sharing the keyed layers (e.g. a policy's flat view)."""

    @abstractmethod
    def users(self, manifest: dict) -> int: ...

    @abstractmethod
    def parameters(self, loaded: LoadedModel) -> int:
        """Parameters a keyed forward computes with (for choosing threads)."""

    @abstractmethod
    def record_files(self, manifest: dict) -> list[str]:
        """The bundle's files besides those ``files`` lists and the manifest (they carry their own hashes)."""

    @property
    @abstractmethod
    def hides_behaviour(self) -> bool:
        """Whether whoever holds the files, without a key, learns nothing of a user's behaviour."""

    @abstractmethod
    def describe(self, manifest: dict) -> str:
        """One line for people (the model card): what this mode keeps where."""


class Unsealed(Mode):
    name = C.MODE_UNSEALED

    def __init__(self, keyed: KeyedModel, encoding: str) -> None:
        self.keyed, self.encoding = keyed, encoding

    @property
    def layer_names(self) -> list[str]:
        return list(self.keyed.layer_names)

    def unlock(self, module: nn.Module, bits: np.ndarray) -> nn.Module:
        return self.keyed.fold(key_codes(bits, self.encoding), module)

    def opens(self, bits: np.ndarray) -> bool:
        return True  # every key runs through the encoder

    def on(self, module: nn.Module) -> Unsealed:
        self.keyed.remove_hooks()  # each layer is scaled once: by the view's hooks from now on
        return Unsealed(self.keyed.on(module).eval(), self.encoding)

    def users(self, manifest: dict) -> int:
        return manifest.get(C.M_KEY, {}).get("users", 1)

    def parameters(self, loaded: LoadedModel) -> int:
        return sum(p.numel() for p in self.keyed.parameters())

    def record_files(self, manifest: dict) -> list[str]:
        return []

    hides_behaviour = False

    def describe(self, manifest: dict) -> str:
        return (
            "**unsealed** (the paper's PRoP): the user's behaviour is trained into the base and a key "
            "encoder, both in these files. Whoever holds them can recover it from the encoder without the "
            "key (docs/threat-model.md); publish unsealed bundles only where that is acceptable."
        )


class Sealed(Mode):
    name = C.MODE_SEALED

    def __init__(self, state: SealedState) -> None:
        self.state = state

    @property
    def layer_names(self) -> list[str]:
        return [layer["name"] for layer in self.state.spec.layers]

    def unlock(self, module: nn.Module, bits: np.ndarray) -> nn.Module | None:
        opened = self.state.open(bits)
        return None if opened is None else opened.payload.fold(module)

    def opens(self, bits: np.ndarray) -> bool:
        return self.state.open(bits) is not None

    def on(self, module: nn.Module) -> Sealed:
        return self  # payloads fold into any module with the keyed layers' names

    def users(self, manifest: dict) -> int:
        return len(manifest.get(C.M_RECORDS, []))

    def parameters(self, loaded: LoadedModel) -> int:
        return sum(p.numel() for p in loaded.module.parameters())

    def record_files(self, manifest: dict) -> list[str]:
        return [r["file"] for r in manifest.get(C.M_RECORDS, [])]

    hides_behaviour = True

    def describe(self, manifest: dict) -> str:
        kind = manifest.get(C.M_PAYLOAD, {}).get("kind")
        return (
            "**sealed**: the base weights are the original checkpoint's; each user's "
            f"{kind} payload is encrypted (AES-256-GCM, key derived with HKDF/scrypt from the "
            "user's key), and a wrong key opens nothing and runs the original."
        )


def load_mode(path: Path, manifest: dict, loaded: LoadedModel) -> Mode:
    """The bundle's mode, from its manifest (the one place a bundle's mode is decided)."""
    if manifest.get(C.M_MODE) == C.MODE_SEALED:
        return Sealed(load_state(path, manifest))
    return Unsealed(_encoder(path, manifest, loaded), manifest[C.M_KEY].get("encoding", C.KEY_ENCODINGS[0]))


def _encoder(path: Path, manifest: dict, loaded: LoadedModel) -> KeyedModel:
    """The key encoder the manifest describes, with its weights, hooked onto the keyed layers."""
    layers = manifest[C.M_KEYED_LAYERS]
    schema.check_layers(layers, loaded.module, str(path))
    enc_meta = manifest[C.M_ENCODER]
    args = dict(
        code_bits=int(manifest[C.M_KEY]["bits"]),
        features=[int(layer["features"]) for layer in layers],
        hidden=list(enc_meta["hidden"]),
        scale=float(enc_meta["scale"]),
    )
    state = read_weights(path / C.ENCODER_WEIGHTS)[0]
    with torch.device("meta"):  # shapes only: nothing is allocated for what the manifest claims
        want = {k: tuple(v.shape) for k, v in KeyEncoder(**args).state_dict().items()}
    got = {k: tuple(v.shape) for k, v in state.items()}
    if got != want:
        diff = sorted(set(got.items()) ^ set(want.items()))[0][0]
        raise PropError(
            f"bundle {path}: {C.ENCODER_WEIGHTS} does not fit the encoder {C.MANIFEST} describes "
            f"(tensor {diff!r} differs)",
            schema.FIX,
        )
    encoder = KeyEncoder(**args)
    encoder.load_state_dict(state)
    keyed = KeyedModel(loaded.module, encoder, [layer["name"] for layer in layers]).eval()
    keyed.batch_axis = {x["name"]: int(x[C.M_BATCH_AXIS]) for x in layers if C.M_BATCH_AXIS in x}
    return keyed
