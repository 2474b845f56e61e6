"""How a bundle turns a key into behaviour: its mode, chosen here and nowhere else.

- ``Unsealed`` (the paper's PRoP): a key encoder over the base, hooked onto the keyed layers; a key
  becomes one delta per keyed layer (Eq. 5).
- ``Sealed``: the base is the original; a key opens its user's encrypted record, whose payload is
  folded into a copy of the base, or opens nothing and the base runs.

In both, a key runs only what its holder enrolled (``enrol``): ``unlock`` is the checked path every
runtime takes (a key enrolled in nothing: None, which ``run.policy.key_opens_nothing`` refuses unless the
caller allows it, and then the base runs; a bundle changed since the key was enrolled, or older than one
this machine has seen (``rollback``): a PropError, nothing runs). ``respond`` is the method itself, any
key through the encoder or the records with no check: what the audit and the paper's reproductions
measure.

Everything downstream (running, the audit, exports, publishing) asks the mode, not the manifest.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch
from torch import nn

from prop_adapters import LoadedModel, read_weights
from prop_cli import constants as C
from prop_cli.core.keyed_model import KeyedModel, KeyEncoder, key_codes
from prop_cli.core.layers import KEYABLE, describe_layer, in_width
from prop_cli.core.payload import payload_elements
from prop_cli.errors import PropError

from . import enrol, rollback
from . import manifest as schema
from .lookup import Index
from .records import SealedState, load_state


class Mode(ABC):
    """What a bundle's mode answers. ``keyed`` is the encoder over the base (unsealed only), ``state``
    the payload layout and encrypted records (sealed only)."""

    name: ClassVar[str]
    keyed: KeyedModel | None = None
    state: SealedState | None = None
    manifest: dict
    where: str = "the bundle"  # how messages name the bundle ("bundle PATH")
    allow_rollback: bool = False  # --allow-rollback: an older copy than one seen here runs, warned

    def seen(self, uid: str | None, version: int) -> None:
        """A key opened enrolment or record ``uid``, written at bundle ``version``, in the bundle as it
        is now: refused if this machine has seen a newer one (``rollback``), else remembered. Once per
        enrolment and command: a command asks its mode several times."""
        done = self.__dict__.setdefault("_seen", set())
        if (uid, version) not in done:
            rollback.opened(self.manifest, uid, version, self.where, self.allow_rollback)
            done.add((uid, version))

    @property
    @abstractmethod
    def layer_names(self) -> list[str]: ...

    @abstractmethod
    def enrolled(self, bits: np.ndarray) -> bool:
        """Whether ``bits`` is enrolled in the bundle as it is now; a PropError ("changed since this key
        was enrolled") if it was enrolled in something else."""

    @abstractmethod
    def respond(self, module: nn.Module, bits: np.ndarray) -> nn.Module | None:
        """The method's response to any key, unchecked: a copy of ``module`` (the base, or a view with
        its keyed layers) under ``bits``, in memory only; None where the key opens nothing."""

    def unlock(self, module: nn.Module, bits: np.ndarray) -> nn.Module | None:
        """What ``bits`` unlocks, checked: its holder's enrolled behaviour, or None where the key is
        enrolled in nothing (``run.policy.key_opens_nothing`` decides what then); a PropError if the bundle
        changed since enrolment."""
        return self.respond(module, bits) if self.enrolled(bits) else None

    def opens(self, bits: np.ndarray) -> bool:
        """Whether ``bits`` unlock a behaviour of their own (checked, as ``unlock``)."""
        return self.enrolled(bits)

    @abstractmethod
    def not_enrolled(self, where: str) -> str:
        """Why a key opens nothing here (the refusal, or the warning where it is allowed): enrolled in
        nothing, or a bundle that cannot say."""

    @abstractmethod
    def on(self, module: nn.Module) -> Mode:
        """The same mode over ``module``, a view sharing the keyed layers (e.g. a policy's flat view)."""

    @classmethod
    @abstractmethod
    def users(cls, manifest: dict) -> int: ...

    @abstractmethod
    def parameters(self, loaded: LoadedModel) -> int:
        """Parameters a keyed forward computes with (for choosing threads)."""

    @classmethod
    @abstractmethod
    def record_files(cls, manifest: dict) -> list[str]:
        """The bundle's files besides those ``files`` lists and the manifest (they carry their own hashes)."""

    # The one name for "this bundle is sealed": whoever holds the files, without a key, learns nothing of a
    # user's behaviour (their payload is ciphertext). Every other module asks Bundle.is_sealed.
    is_sealed: ClassVar[bool]

    @classmethod
    @abstractmethod
    def describe(cls, manifest: dict) -> str:
        """One line for people (the model card): what this mode keeps where."""

    @classmethod
    def require_independent_users(cls, command: str, path: Path) -> None:
        """Commands that add or remove one user alone (add-user, remove-user) need users that do not
        share weights: a sealed bundle's records. Unsealed users share one encoder and base."""
        if not cls.is_sealed:
            raise PropError(
                f"{command} works on sealed bundles; {path} is unsealed (its users share one encoder and "
                "base, trained together)",
                "personalize again with every user's data, or with --seal to make users independent",
            )

    @classmethod
    def require_shared_enrolment(cls, path: Path) -> None:
        """`prop enrol` enrols a key in the bundle's shared enrolments: an unsealed bundle's. A sealed
        bundle enrols each user in their own record (add-user)."""
        if cls.is_sealed:
            raise PropError(
                f"{path} is sealed: each user is enrolled in their own record",
                "add a user with prop add-user (their record is their enrolment)",
            )

    @classmethod
    @abstractmethod
    def exposed(cls) -> str | None:
        """What whoever holds the files can read without a key (push refuses a public upload of it);
        None: nothing of any user's behaviour."""

    @classmethod
    @abstractmethod
    def public_metrics(cls, manifest: dict) -> dict | None:
        """The final metrics the model card may show; None: they are sealed with each user's record."""

    @classmethod
    @abstractmethod
    def facts(cls, manifest: dict) -> dict:
        """What `prop inspect BUNDLE` shows of this mode (``bundle.describe``)."""

    def payload_for(self, bits: np.ndarray):
        """The payload ``bits`` opens (``core.payload.Payload``), checked as ``unlock`` checks it; None:
        the key opens nothing. Only sealed bundles keep payloads."""
        raise PropError(
            "this bundle is unsealed: its users' behaviour is in its base and encoder, not in a payload",
            "personalize again with --seal --payload peft-lora, the one payload export --peft takes",
        )


NOT_ENROLLED = (
    "the key is enrolled in nothing in {where}; the bundle may have been replaced or the user removed"
)


class Unsealed(Mode):
    name = C.MODE_UNSEALED

    def __init__(self, keyed: KeyedModel, encoding: str, manifest: dict) -> None:
        self.keyed, self.encoding, self.manifest = keyed, encoding, manifest
        self.version = manifest[C.M_FORMAT]
        self.entries = manifest.get(C.M_ENROLMENTS, [])
        self.index = Index.of(self.entries, manifest)  # format 6: a key opens the enrolment named for it
        self.current = enrol.behaviour(manifest)

    @property
    def layer_names(self) -> list[str]:
        return list(self.keyed.layer_names)

    def enrolled(self, bits: np.ndarray) -> bool:
        # Before format 4 nothing was enrolled: whoever wrote the files chose the encoder, so no key runs
        # through it unchecked (an attacker can write an old format too). `prop enrol` opts in.
        if self.version < C.ENROL_SINCE:
            return False
        opened = enrol.check(self.entries, bits, self.current, self.where, self.index)
        if opened is None:
            return False
        self.seen(opened.get(enrol.ID), int(opened.get(enrol.VERSION, 0)))
        return True

    def respond(self, module: nn.Module, bits: np.ndarray) -> nn.Module:
        return self.keyed.fold(key_codes(bits, self.encoding), module)

    def not_enrolled(self, where: str) -> str:
        if self.version < C.ENROL_SINCE:
            return (
                f"{where} is a format {self.version} bundle, from before keys were enrolled: prop cannot "
                f"tell whether it changed since your key was used (if you trust it: prop enrol {where} "
                "--key-file ...)"
            )
        return NOT_ENROLLED.format(where=where)

    def on(self, module: nn.Module) -> Unsealed:
        self.keyed.remove_hooks()  # each layer is scaled once: by the view's hooks from now on
        view = Unsealed(self.keyed.on(module).eval(), self.encoding, self.manifest)
        view.where, view.allow_rollback = self.where, self.allow_rollback
        return view

    @classmethod
    def users(cls, manifest: dict) -> int:
        return manifest.get(C.M_KEY, {}).get("users", 1)

    def parameters(self, loaded: LoadedModel) -> int:
        return sum(p.numel() for p in self.keyed.parameters())

    @classmethod
    def record_files(cls, manifest: dict) -> list[str]:
        return []

    is_sealed = False

    @classmethod
    def exposed(cls) -> str | None:
        return "whoever downloads it can read the owner's behaviour off its encoder"

    @classmethod
    def public_metrics(cls, manifest: dict) -> dict | None:
        return manifest.get(C.M_METRICS, {})

    @classmethod
    def facts(cls, manifest: dict) -> dict:
        return {"users": cls.users(manifest)}  # users whose keys were trained (and enrolled, format 4)

    @classmethod
    def describe(cls, manifest: dict) -> str:
        return (
            "**unsealed** (the paper's PRoP): the user's behaviour is trained into the base and a key "
            "encoder, both in these files. Whoever holds them can recover it from the encoder without the "
            "key (docs/threat-model.md); publish unsealed bundles only where that is acceptable."
        )


class Sealed(Mode):
    name = C.MODE_SEALED

    def __init__(self, state: SealedState) -> None:
        self.state = state
        self.manifest = state.manifest

    @property
    def layer_names(self) -> list[str]:
        return [layer["name"] for layer in self.state.spec.layers]

    @property
    def _unbound_files(self) -> list[str]:
        # Format 2-3 records bound the base weights but not an adapter's own files (LeRobot processors).
        return [] if self.state.enrolled else sorted(set(self.state.manifest[C.M_FILES]) - {C.BASE_WEIGHTS})

    def _checked(self, bits: np.ndarray):
        """The record ``bits`` opens, checked (enrolment, then rollback); None: it runs nothing."""
        opened = self.state.open(bits)
        if opened is None or self._unbound_files:
            return None
        if opened.changed:
            raise enrol.changed_error(self.where, opened.changed)
        self.seen(opened.record_id, opened.version)
        return opened

    def enrolled(self, bits: np.ndarray) -> bool:
        return self._checked(bits) is not None

    def respond(self, module: nn.Module, bits: np.ndarray) -> nn.Module | None:
        opened = self.state.open(bits)
        return None if opened is None else opened.payload.fold(module)

    def unlock(self, module: nn.Module, bits: np.ndarray) -> nn.Module | None:
        opened = self._checked(bits)  # one trial decryption for both the check and the payload
        return None if opened is None else opened.payload.fold(module)

    def payload_for(self, bits: np.ndarray):
        opened = self._checked(bits)
        return None if opened is None else opened.payload

    def not_enrolled(self, where: str) -> str:
        if self._unbound_files:
            return (
                f"{where} is a format {self.state.manifest[C.M_FORMAT]} sealed bundle whose records do not "
                f"bind {', '.join(self._unbound_files[:3])}: your key runs nothing (personalize it again)"
            )
        return NOT_ENROLLED.format(where=where)

    def on(self, module: nn.Module) -> Sealed:
        return self  # payloads fold into any module with the keyed layers' names

    @classmethod
    def users(cls, manifest: dict) -> int:
        return len(manifest.get(C.M_RECORDS, []))

    @classmethod
    def facts(cls, manifest: dict) -> dict:
        # Records, not users: each opens with one key, and the manifest cannot say whose.
        payload = manifest.get(C.M_PAYLOAD, {})
        return {"records": cls.users(manifest), "payload": {k: payload.get(k) for k in ("kind", "rank")}}

    def parameters(self, loaded: LoadedModel) -> int:
        return sum(p.numel() for p in loaded.module.parameters())

    @classmethod
    def record_files(cls, manifest: dict) -> list[str]:
        return [r["file"] for r in manifest.get(C.M_RECORDS, [])]

    is_sealed = True

    @classmethod
    def exposed(cls) -> str | None:
        return None

    @classmethod
    def public_metrics(cls, manifest: dict) -> dict | None:
        return None

    @classmethod
    def describe(cls, manifest: dict) -> str:
        kind = manifest.get(C.M_PAYLOAD, {}).get("kind")
        return (
            "**sealed**: the base weights are the original checkpoint's; each user's "
            f"{kind} payload is encrypted (AES-256-GCM, key derived with HKDF/scrypt from the "
            "user's key), and a wrong key opens nothing: prop refuses it, or with "
            "--allow-unenrolled-key runs the original."
        )


# The manifest's keyed layers against the model they key: here, where the model is (the schema is data).
def _keyable(mods: dict, layer: dict, where: str, source: str, mode: str = C.MODE_UNSEALED):
    """The model's layer a manifest entry names, refused unless it is a linear layer or convolution."""
    m = mods.get(layer["name"])
    if not isinstance(m, KEYABLE):
        problem = f"names no linear layer or convolution of the model ({layer['name']!r})"
        raise schema.field_error(source, f"{where}.name", problem, mode)
    return m


def check_layers(layers: list[dict], module, source: str) -> None:
    """Each keyed layer is a linear layer or convolution of ``module`` with the recorded input width."""
    mods = dict(module.named_modules())
    for i, layer in enumerate(layers):
        where = f"{C.M_KEYED_LAYERS}[{i}]"
        m = _keyable(mods, layer, where, source)
        if in_width(m) != layer["features"]:
            raise schema.field_error(
                source, f"{where}.features", f"is {layer['features']} but layer {layer['name']!r} takes "
                f"{in_width(m)} inputs",
            )  # fmt: skip


# A payload layout may hold this many numbers beyond 8 per weight of its layers (a LoRA of any useful
# rank holds at most 2): room for ranks above a small layer's width, never a layout of gigabytes.
PAYLOAD_SLACK = 1 << 16


def check_payload_layers(layers: list[dict], rank: int, elements: int, module, source: str) -> None:
    """Each layer of a sealed payload's layout is a linear layer or convolution of ``module``, recorded
    as it is (widths, kernel, groups), and the layout's size (``elements``, at ``rank``) is bounded by
    those layers' weights: nothing is allocated for sizes the model does not have."""
    mods = dict(module.named_modules())
    weights = 0
    for i, layer in enumerate(layers):
        where = f"{C.M_PAYLOAD}.layers[{i}]"
        m = _keyable(mods, layer, where, source, C.MODE_SEALED)
        actual = describe_layer(layer["name"], m)
        if actual != layer:
            raise schema.field_error(
                source, where, f"is {schema.quoted(layer)} but the model's layer is {actual}", C.MODE_SEALED
            )
        weights += m.weight.numel()
    if elements > 8 * weights + PAYLOAD_SLACK:
        raise schema.field_error(
            source, f"{C.M_PAYLOAD}.rank",
            f"is {rank}: a payload of {elements} numbers for layers of {weights} weights", C.MODE_SEALED,
        )  # fmt: skip


def mode_of(manifest: dict) -> type[Mode]:
    """The mode a manifest declares, without loading anything (push, verify, inspect, enrol)."""
    return Sealed if manifest.get(C.M_MODE) == C.MODE_SEALED else Unsealed


def load_mode(path: Path, manifest: dict, loaded: LoadedModel, allow_rollback: bool = False) -> Mode:
    """The bundle's mode, from its manifest (the one place a bundle's mode is decided)."""
    if mode_of(manifest) is Sealed:
        state = load_state(path, manifest)
        spec = state.spec
        check_payload_layers(spec.layers, spec.rank, payload_elements(spec), loaded.module, str(path))
        mode: Mode = Sealed(state)
    else:
        encoding = manifest[C.M_KEY].get("encoding", C.KEY_ENCODINGS[0])
        mode = Unsealed(_encoder(path, manifest, loaded), encoding, manifest)
    mode.where, mode.allow_rollback = f"bundle {path}", allow_rollback
    return mode


def _encoder(path: Path, manifest: dict, loaded: LoadedModel) -> KeyedModel:
    """The key encoder the manifest describes, with its weights, hooked onto the keyed layers."""
    layers = manifest[C.M_KEYED_LAYERS]
    check_layers(layers, loaded.module, str(path))
    enc_meta = manifest[C.M_ENCODER]
    args = dict(
        code_bits=int(manifest[C.M_KEY]["bits"]),
        features=[int(layer["features"]) for layer in layers],
        hidden=list(enc_meta["hidden"]),
        scale=float(enc_meta["scale"]),
    )
    state = read_weights(path / C.ENCODER_WEIGHTS, safetensors_only=True)[0]
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
