"""ONNX export of a bundle (`prop export --onnx`) and running an export (`prop run --onnx`): each mode's
graphs in its own module (``unsealed``, ``sealed``), chosen here; the shared plumbing in ``common``.

Exporter: torch's TorchScript-based exporter (``dynamo=False``). It needs no extra package (the
torch.export-based one needs onnxscript), works offline and supports ``dynamic_axes``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from prop_cli import constants as C
from prop_cli.bundle import Bundle
from prop_cli.bundle.manifest import stamp
from prop_cli.bundle.modes import mode_of
from prop_cli.config import ExportSettings
from prop_cli.errors import PropError, plural
from prop_cli.files import EXPORT, check_output, dump_json, no_links, put
from prop_cli.run.policy import key_opens_nothing, require_enrolled

from . import sealed, unsealed
from .common import (
    REEXPORT,
    ExportResult,
    bound,
    check_current,
    read_export,
    refuse_link,
    require_onnx,
    session,
    verify_inputs,
)
from .sealed import SealedOnnxRunner, add_record, drop_record
from .unsealed import DeltaInputView, OnnxRunner, delta_names

__all__ = [
    "DeltaInputView",
    "ExportResult",
    "OnnxRunner",
    "SealedOnnxRunner",
    "add_record",
    "delta_names",
    "describe_export",
    "drop_record",
    "export_onnx",
    "follow",
    "read_export",
    "require_onnx",
    "run_onnx",
    "session",
    "verify_graphs",
]


def _mode(bundle: Bundle):
    return sealed if bundle.is_sealed else unsealed


def export_onnx(
    bundle: Bundle,
    out: Path | None = None,
    settings: ExportSettings | None = None,
    *,
    key: np.ndarray | None = None,
    inputs: np.ndarray | None = None,
    force: bool = False,
    allow_unenrolled: bool = False,
) -> ExportResult:
    """Write the bundle's graphs to ``out`` (default ``<bundle>/onnx``) and verify them with onnxruntime.

    Verification compares onnxruntime with torch for the null key, a random key and ``key`` (the
    user's, if given) on ``inputs`` (or random inputs of the bundle's input shape). Files are
    written to a temporary folder and renamed into place only if every difference is <= ``atol``;
    otherwise nothing is left behind and ``ok`` is False. ``key`` is bound to the graphs; a key enrolled
    in nothing of the bundle is refused (``allow_unenrolled``: verified with, bound to nothing).
    """
    s = (settings or ExportSettings()).validate()
    require_onnx()
    binds = key is not None and require_enrolled(bundle, key, allow_unenrolled)
    out = Path(out) if out is not None else no_links(Path(bundle.path), C.EXPORT_DIR)
    refuse_link(out, "export folder", "remove the link, or choose another --out")
    check_output(out, force, what="export folder", kind=EXPORT)

    def verify(folder: Path) -> list[dict]:
        return verify_graphs(bundle, folder, key=key, inputs=inputs, seed=s.seed, atol=s.atol)

    return _mode(bundle).export(bundle, out, s, key if binds else None, verify)


def verify_graphs(
    bundle: Bundle,
    folder: Path,
    *,
    key: np.ndarray | None = None,
    inputs: np.ndarray | None = None,
    seed: int = 0,
    atol: float = ExportSettings.atol,
) -> list[dict]:
    """onnxruntime vs torch for every graph in ``folder`` and every key: a list of table rows."""
    rng = np.random.default_rng(seed)
    x = verify_inputs(bundle, inputs, rng)
    return _mode(bundle).verify(bundle, folder, key, x, rng, atol)


def run_onnx(
    bundle: Bundle, x: np.ndarray, key: np.ndarray | None, folder: Path | None = None, threads: int = 0,
    *, allow_unenrolled: bool = False,
) -> np.ndarray:  # fmt: skip
    """`prop run --onnx`: the bundle's outputs computed by its exported graphs (folded where possible).
    A key enrolled in nothing of the bundle is refused, as with torch (``allow_unenrolled``: base.onnx
    runs, with a warning); an enrolled key runs only where the export binds it.

    ``threads``: onnxruntime's intra-op threads (0: ``OMP_NUM_THREADS`` if set, else onnxruntime's choice)."""
    require_onnx()
    folder = Path(folder) if folder is not None else no_links(Path(bundle.path), C.EXPORT_DIR)
    if not folder.is_dir():
        raise PropError(
            f"no ONNX export at {folder}", "run prop export BUNDLE --onnx first, or pass --onnx-dir"
        )
    meta = read_export(folder, bundle.manifest)
    threads = threads or int(os.environ.get("OMP_NUM_THREADS", "0") or 0)
    if key is not None and not require_enrolled(bundle, key, allow_unenrolled):
        key_opens_nothing(bundle.mode.not_enrolled(str(bundle.path)), allow_unenrolled, stacklevel=3)
        key = None  # allowed: exactly base.onnx, as torch runs the base (whatever the export binds)
    if key is not None:
        # A key enrolled in the bundle runs its export only where the export binds it to its graphs.
        if not bound(meta, key, folder, bundle.manifest):
            raise PropError(
                f"the ONNX export in {folder} is not bound to this key (exported without it, or replaced "
                "since): its graphs are not checked against your key",
                f"export it again with your key: prop export {bundle.path} --onnx --key-file KEY --force",
            )
    return _mode(bundle).run(bundle, folder, x, key, threads)


def describe_export(folder: Path, manifest: dict) -> dict | None:
    """What `prop inspect BUNDLE` says of the export in ``folder`` (``<bundle>/onnx``): None where there
    is none; else whether it is current (made from the bundle as it is, its graphs unmodified, and for
    a sealed bundle holding the same records), why not, and how many keys it binds. Read as data: onnx
    need not be installed."""
    folder = Path(folder)
    if not folder.exists():
        return None
    state = {"folder": str(folder), "current": True, "why": None, "fix": None, "bound_keys": 0}
    try:
        meta = read_export(folder)
    except PropError as e:
        return {**state, "current": False, "why": e.what, "fix": REEXPORT}
    state["bound_keys"] = len(meta.get(C.M_ENROLMENTS, []))
    # Sealed exports carry the records (unsealed: none on either side, nothing to compare).
    want = set(mode_of(manifest).record_files(manifest))
    public = meta.get("sealed") or {}
    have = set(mode_of(public).record_files(public))
    if want or have:
        state["records"] = len(have & want)
    if have != want:
        extra = f" and {len(have - want)} the bundle no longer has" if have - want else ""
        why = f"it holds {len(have & want)} of the bundle's {plural(len(want), 'user record')}{extra}"
        return {**state, "current": False, "why": why, "fix": REEXPORT}
    try:
        check_current(meta, folder, manifest)
    except PropError as e:
        state.update(current=False, why=e.what, fix=REEXPORT)
    return state


def follow(folder: Path, old: dict, new: dict) -> None:
    """After a write of the bundle that changed neither its files nor its records (a recorded audit,
    `prop enrol`): the export in ``folder`` (``<bundle>/onnx``) takes the new version, if it was the
    export of the bundle as it was (``old``), so that it stays the bundle's; else it is left as it is
    (``describe_export`` says why). Nothing is written through a link."""
    folder = Path(folder)
    if folder.is_symlink() or not (folder / C.EXPORT_META).is_file():
        return
    same = {k: new.get(k) for k in (C.M_FILES, C.M_RECORDS, C.M_BUNDLE_ID)}
    if same != {k: old.get(k) for k in same} or C.M_BUNDLE_VERSION not in new:
        return
    try:
        meta = read_export(folder, old)
    except PropError:
        return
    meta[C.M_BUNDLE_VERSION] = new[C.M_BUNDLE_VERSION]
    # Through the bundle's descriptor where its lock is held (enrol's, record_audit's): no link followed.
    put(folder, C.EXPORT_META, dump_json(stamp(meta, C.EXPORT_DIGEST)).encode(), "export", output=True)
