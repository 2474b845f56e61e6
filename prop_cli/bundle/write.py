"""Writing a bundle: base weights, the mode's part (encoder weights, or encrypted records) and the
manifest, in a directory.

Each file is written once, into a temporary sibling directory renamed into place at the end, so an
interrupted run never leaves a half bundle at the output path. No key material and no key hash is
ever written.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
from safetensors import safe_open
from safetensors.torch import save_file

from prop_adapters import LoadedModel
from prop_adapters.hub import public_name
from prop_cli import __version__
from prop_cli import constants as C
from prop_cli.core.key_files import KeySource, kdf_record
from prop_cli.core.keyed_model import KeyedModel
from prop_cli.core.payload import Payload, PayloadSpec
from prop_cli.errors import PropError
from prop_cli.files import bundle_lock, check_output, dump_json, put, sha256_file, staged_dir

from . import manifest as schema
from . import rollback
from .enrol import enrol, new_id
from .read import read_manifest
from .records import SealedState, record_entry, seal_payload, write_record

# (payload, what is sealed beside it, key bits) of one sealed user.
SealedUserParts = tuple[Payload, dict, np.ndarray]


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
    io = dict(full.get(C.M_IO, {}))
    io.pop("checkpoint", None)
    name = public_name(manifest.get(C.M_IO, {}).get("checkpoint"))  # a file name: never a local path
    full[C.M_IO] = {**io, **({"checkpoint": name} if name else {})}
    full[C.M_FORMAT] = C.FORMAT_VERSION
    full[C.M_PROP_VERSION] = __version__
    full.update(schema.new_identity())  # a new bundle: a new id, version 1
    full[C.M_FILES] = {n: sha256_file(tmp / n) for n in files}
    return full


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


def write_unsealed(
    out: Path,
    *,
    loaded: LoadedModel,
    keyed: KeyedModel,
    manifest: dict,
    keys: list[np.ndarray],
    force: bool = False,
    copy_base: bool = False,
) -> dict:
    """Write an unsealed bundle: the trained base, the key encoder, and an enrolment per user (``keys``:
    their key bits, never written). ``copy_base`` copies the input checkpoint's bytes (a frozen base
    from safetensors). Returns the manifest written."""
    out = Path(out)
    check_output(out, force)
    with bundle_lock(out), staged_dir(out) as tmp:  # --force over a bundle: not while another writes it
        _write_base(tmp, loaded, keyed.module, copy_base)
        enc = {k: v.detach().cpu().contiguous() for k, v in keyed.encoder.state_dict().items()}
        save_file(enc, str(tmp / C.ENCODER_WEIGHTS))
        extra = _adapter_files(tmp, loaded, tmp / C.BASE_WEIGHTS)
        names = (C.BASE_WEIGHTS, C.ENCODER_WEIGHTS, *extra)
        full = _stamp({**manifest, C.M_MODE: C.MODE_UNSEALED}, tmp, names)
        full = schema.stamp({**full, C.M_ENROLMENTS: enrol(full, keys)})
        (tmp / C.MANIFEST).write_text(dump_json(full))
    rollback.wrote(full)
    return full


def write_sealed(
    out: Path,
    *,
    loaded: LoadedModel,
    manifest: dict,
    users: list[SealedUserParts],
    metrics: Callable[[SealedState], dict] | None = None,
    force: bool = False,
) -> dict:
    """Write a sealed bundle: the original's weights as the base, and one encrypted record per user.
    ``metrics(state)`` is called with the records as written (keys are tried on them as anyone would)
    before the manifest is; what it returns (if not None) is the manifest's metrics. Returns the
    manifest written."""
    out = Path(out)
    check_output(out, force)
    with bundle_lock(out), staged_dir(out) as tmp:  # --force over a bundle: not while another writes it
        copy_base = str(loaded.source).endswith(".safetensors")
        _write_base(tmp, loaded, loaded.module, copy_base)
        extra = _adapter_files(tmp, loaded, tmp / C.BASE_WEIGHTS)
        full = _stamp({**manifest, C.M_MODE: C.MODE_SEALED, C.M_RECORDS: []}, tmp, (C.BASE_WEIGHTS, *extra))
        records = []
        for payload, private, bits in users:
            rec = seal_payload(full, private, payload, bits)
            write_record(tmp, rec)
            full[C.M_RECORDS].append(record_entry(rec))
            records.append(rec)
        if metrics is not None:
            public = metrics(SealedState(full, PayloadSpec.from_dict(full[C.M_PAYLOAD]), records))
            if public is not None:
                full[C.M_METRICS] = public
        full = schema.stamp(full)
        (tmp / C.MANIFEST).write_text(dump_json(full))
    rollback.wrote(full, users={rec.id: full[C.M_BUNDLE_VERSION] for rec in records})
    return full


def update_manifest(path: Path, key: str, value: dict) -> None:
    """Set one manifest entry (e.g. the audit summary), atomically, as the bundle's next version; weights
    are untouched. Under the bundle's write lock, from the read to the write."""
    bundle = Path(path)
    with bundle_lock(bundle):
        manifest = schema.next_version(read_manifest(bundle), str(bundle))
        manifest[key] = value
        manifest = schema.restamp(manifest)
        put(bundle, C.MANIFEST, dump_json(manifest).encode(), output=True)
        rollback.wrote(manifest)


def enrol_key(path: Path, manifest: dict, bits: np.ndarray) -> tuple[dict, str]:
    """Enrol ``bits`` in the unsealed bundle at ``path`` as it is now (the key holder's consent to its
    current behaviour), replacing that key's earlier enrolment (whose id it keeps, at the new version:
    the older one is refused here from now on); a format 1-4 bundle becomes format 5 (a new bundle id,
    version 1; the other users' enrolments stay as they were). Returns the manifest written and what
    happened: "enrolled", "re-enrolled: <changes>" or "already enrolled" (nothing written). A sealed
    bundle is refused (each of its users is enrolled in their own record), and a key of another size."""
    from .enrol import ID, behaviour, changed, split
    from .lookup import Index
    from .modes import mode_of

    mode_of(manifest).require_shared_enrolment(path)
    n = int(manifest[C.M_KEY]["bits"])
    if len(bits) != n:
        raise PropError(f"the key has {len(bits)} bits but the bundle expects {n}", "use the bundle's key")
    entries = manifest.get(C.M_ENROLMENTS, [])
    kept, opened = split(entries, bits, Index.of(entries, manifest))
    diff = changed(opened.get("behaviour", {}), behaviour(manifest)) if opened is not None else None
    if manifest[C.M_FORMAT] >= C.ENROL_SINCE and opened is not None and not diff:
        return manifest, "already enrolled"
    if C.M_BUNDLE_ID in manifest:
        new = schema.next_version(manifest, str(path))
    else:  # from before bundle ids: this write names the bundle
        new = {**manifest, **schema.new_identity()}
    new.update({C.M_FORMAT: C.FORMAT_VERSION, C.M_MODE: C.MODE_UNSEALED})
    name = public_name(manifest[C.M_IO].get("checkpoint"))
    new[C.M_IO] = {k: v for k, v in manifest[C.M_IO].items() if k != "checkpoint"}
    new[C.M_IO].update({"checkpoint": name} if name else {})
    uid = (opened or {}).get(ID) or new_id()
    new[C.M_ENROLMENTS] = kept + enrol(new, [bits], [uid])
    new = schema.validate(schema.stamp(new), str(path))
    with bundle_lock(Path(path)):  # the caller's (api.enrol holds it from before it read ``manifest``)
        put(Path(path), C.MANIFEST, dump_json(new).encode(), output=True)
        rollback.wrote(new, users={uid: new[C.M_BUNDLE_VERSION]})
    return new, ("re-enrolled (the bundle changed: " + ", ".join(diff) + ")" if diff else "enrolled")


def describe_layers(keyed: KeyedModel) -> list[dict]:
    """The manifest's ``keyed_layers`` of an encoder-keyed model (with batch axes that are not 0)."""
    out = [{"name": n, "features": f} for n, f in zip(keyed.layer_names, keyed.encoder.features)]
    for layer in out:
        if keyed.batch_axis.get(layer["name"], 0):
            layer[C.M_BATCH_AXIS] = keyed.batch_axis[layer["name"]]
    return out


def common_fields(
    loaded: LoadedModel, keys: list[KeySource], salt: bytes | None, config: dict, checkpoint: str
) -> dict:
    """The manifest fields every mode writes alike: the model spec, the key (its size, where it came from,
    the passphrase KDF; never the key or its hash), the training settings and the checkpoint's public
    name (a hub path or none: a local path stays private)."""
    kinds = sorted({k.kind for k in keys})
    name = public_name(checkpoint)
    return {
        C.M_MODEL: loaded.spec,
        C.M_KEY: {
            "bits": len(keys[0].bits),
            "source": kinds[0] if len(kinds) == 1 else "mixed",
            "kdf": kdf_record(salt),
        },
        C.M_CONFIG: config,
        C.M_IO: {"checkpoint": name} if name else {},
    }
