"""The bundle `prop personalize` writes: base weights, encoder weights and a manifest, in a directory.

Written to a temporary sibling directory and renamed into place at the end, so an interrupted run
never leaves a half bundle at the output path. No key material and no key hash is ever written.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from safetensors import safe_open
from safetensors.torch import save_file

import prop_adapters
from prop_adapters import LoadedModel

from . import __version__
from . import constants as C
from . import manifest as schema
from .errors import PropError
from .files import check_output, dump_json, sha256_file, staged_dir, write_text
from .keyed import KeyedModel, KeyEncoder
from .payload import Payload

if TYPE_CHECKING:
    from .sealed import SealedState


def _safetensors_metadata(path: str) -> dict[str, str] | None:
    if not path.endswith(".safetensors"):
        return None
    with safe_open(path, framework="pt") as f:
        return f.metadata()


def _write_base(tmp: Path, loaded: LoadedModel, module, copy_base: bool) -> None:
    base_path = tmp / C.BASE_WEIGHTS
    if copy_base:
        shutil.copyfile(loaded.source, base_path)
        return
    state = {k: v.detach().to("cpu").contiguous() for k, v in loaded.extra.items()}
    state.update(
        (k, v.detach().to("cpu", loaded.dtypes.get(k, v.dtype)).contiguous())
        for k, v in module.state_dict().items()
    )
    save_file(state, str(base_path), metadata=_safetensors_metadata(loaded.source))


def _stamp(manifest: dict, tmp: Path, files: tuple[str, ...]) -> dict:
    full = dict(manifest)
    full[C.M_FORMAT] = C.FORMAT_VERSION
    full[C.M_PROP_VERSION] = __version__
    full[C.M_FILES] = {n: sha256_file(tmp / n) for n in files}
    return full


def write_bundle(
    out: Path,
    *,
    loaded: LoadedModel,
    keyed: KeyedModel,
    manifest: dict,
    force: bool = False,
    copy_base: bool = False,
) -> Path:
    """Write the bundle. ``copy_base`` copies the input checkpoint's bytes (frozen base, safetensors)."""
    out = Path(out)
    check_output(out, force)
    with staged_dir(out) as tmp:
        _write_base(tmp, loaded, keyed.module, copy_base)
        enc = {k: v.detach().cpu().contiguous() for k, v in keyed.encoder.state_dict().items()}
        save_file(enc, str(tmp / C.ENCODER_WEIGHTS))
        extra = _adapter_files(tmp, loaded, tmp / C.BASE_WEIGHTS)
        names = (C.BASE_WEIGHTS, C.ENCODER_WEIGHTS, *extra)
        full = _stamp({**manifest, C.M_MODE: C.MODE_UNSEALED}, tmp, names)
        (tmp / C.MANIFEST).write_text(dump_json(schema.stamp(full)))
    return out


def _adapter_files(tmp: Path, loaded: LoadedModel, base_path: Path) -> list[str]:
    """The adapter's own files (e.g. a LeRobot folder's config and processors) and the base's alias."""
    written = []
    for rel, data in loaded.files.items():
        (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp / rel).write_bytes(data)
        written.append(rel)
    if loaded.base_alias:
        alias = tmp / loaded.base_alias
        alias.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(base_path, alias)  # the same bytes, no second copy on disk
        except OSError:
            shutil.copyfile(base_path, alias)
        written.append(loaded.base_alias)
    return written


def write_sealed_bundle(
    out: Path,
    *,
    loaded: LoadedModel,
    manifest: dict,
    users: list[tuple[Payload, dict, np.ndarray]],
    force: bool = False,
) -> dict:
    """Write a sealed bundle: the original's weights as the base, and one encrypted record per user
    ``(payload, private metadata, key bits)``. Returns the manifest written."""
    from .sealed import record_entry, seal_payload, write_record

    out = Path(out)
    check_output(out, force)
    with staged_dir(out) as tmp:
        copy_base = str(loaded.source).endswith(".safetensors")
        _write_base(tmp, loaded, loaded.module, copy_base)
        extra = _adapter_files(tmp, loaded, tmp / C.BASE_WEIGHTS)
        full = _stamp({**manifest, C.M_MODE: C.MODE_SEALED, C.M_RECORDS: []}, tmp, (C.BASE_WEIGHTS, *extra))
        for payload, meta, bits in users:
            rec = seal_payload(full, meta, payload, bits)
            full[C.M_RECORDS].append(record_entry(rec, write_record(tmp, rec)))
        full = schema.stamp(full)
        (tmp / C.MANIFEST).write_text(dump_json(full))
    return full


def update_manifest(path: Path, key: str, value: dict) -> None:
    """Set one manifest entry (e.g. the audit summary), atomically; weights are untouched."""
    bundle = Path(path)
    manifest = read_manifest(bundle)
    manifest[key] = value
    write_text(bundle / C.MANIFEST, dump_json(schema.restamp(manifest)), what="manifest", flag="BUNDLE")


def read_manifest(path: Path) -> dict:
    path = Path(path)
    if not path.exists():
        raise PropError(
            f"bundle {path} does not exist", "check the path (a directory made by prop personalize)"
        )
    mpath = path / C.MANIFEST
    if not path.is_dir() or not mpath.is_file():
        raise PropError(
            f"{path} is not a prop bundle (no {C.MANIFEST})",
            "pass the directory written by prop personalize --out",
        )
    try:
        raw = mpath.read_bytes()
    except OSError as e:
        raise PropError(
            f"bundle {path}: {C.MANIFEST} cannot be read ({e.strerror})", "check its permissions"
        ) from None
    return schema.parse(raw, str(path))


@dataclass
class Bundle:
    """A loaded bundle. Unsealed: ``keyed`` is the base with its key encoder. Sealed: ``keyed`` is
    None (there is no encoder) and ``sealed`` holds the payload layout and the encrypted records."""

    path: Path
    manifest: dict
    loaded: LoadedModel
    keyed: KeyedModel | None
    sealed: SealedState | None = None

    @property
    def is_sealed(self) -> bool:
        return self.sealed is not None

    @property
    def layer_names(self) -> list[str]:
        if self.sealed is not None:
            return [layer["name"] for layer in self.sealed.spec.layers]
        return list(self.keyed.layer_names)

    @property
    def task(self) -> str:
        return self.manifest[C.M_TASK]

    @property
    def key_bits(self) -> int:
        return int(self.manifest[C.M_KEY]["bits"])

    @property
    def key_encoding(self) -> str:
        # Sealed bundles have no encoder and record none; the audit's blank encoder hashes like the default.
        return self.manifest[C.M_KEY].get("encoding", C.KEY_ENCODINGS[0])

    def check_key(self, key: np.ndarray, what: str = "the key") -> np.ndarray:
        if len(key) != self.key_bits:
            raise PropError(
                f"{what} has {len(key)} bits but the bundle expects {self.key_bits}",
                "use the key the bundle was personalized with",
            )
        return key


def load_bundle(path: Path) -> Bundle:
    """Load and verify (format version, manifest schema and digest, sha256 of every file) a bundle."""
    path = Path(path)
    manifest = read_manifest(path)
    check_files(path, manifest)
    loaded = prop_adapters.rebuild(manifest[C.M_MODEL], _weights(path / C.BASE_WEIGHTS), str(path))
    if manifest.get(C.M_MODE) == C.MODE_SEALED:
        from .sealed import load_state

        return Bundle(path, manifest, loaded, None, load_state(path, manifest))
    return Bundle(path, manifest, loaded, _keyed(path, manifest, loaded))


def check_files(path: Path, manifest: dict) -> None:
    """Every file the manifest lists is there and has the sha256 the manifest records."""
    for name, digest in manifest[C.M_FILES].items():
        f = path / name
        if not f.is_file():
            raise PropError(f"bundle {path} is missing {name}", "write the bundle again")
        if digest != sha256_file(f):
            raise PropError(
                f"bundle {path}: {name} does not match its sha256 in {C.MANIFEST} (modified or corrupt)",
                "restore the bundle from a trusted copy",
            )


def _weights(path: Path) -> dict:
    return prop_adapters.read_weights(path)[0]


def _keyed(path: Path, manifest: dict, loaded: LoadedModel) -> KeyedModel:
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
    state = _weights(path / C.ENCODER_WEIGHTS)
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


def describe_layers(keyed: KeyedModel) -> list[dict]:
    out = [{"name": n, "features": f} for n, f in zip(keyed.layer_names, keyed.encoder.features)]
    for layer in out:
        if keyed.batch_axis.get(layer["name"], 0):
            layer[C.M_BATCH_AXIS] = keyed.batch_axis[layer["name"]]
    return out
