"""ONNX export of a sealed bundle, and running it.

A sealed bundle exports as ``base.onnx`` (the original) plus its encrypted records: the runtime
(``SealedOnnxRunner``) opens the user's record with their key and folds the payload into the keyed
layers' initializers in this process's memory. No graph holds a payload in the clear.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import torch

from prop_cli import constants as C
from prop_cli.bundle import Bundle
from prop_cli.bundle.enrol import changed_error
from prop_cli.bundle.manifest import Doc, quoted, stamp
from prop_cli.bundle.records import copy_records, load_state, public_part, read_record
from prop_cli.config import ExportSettings
from prop_cli.errors import PropError, brief
from prop_cli.files import delete, dump_json, no_links, put, sha256_file, staged_dir

from ..policy import KeyedPolicy
from . import common
from .common import ExportResult, VerificationFailed


def export(bundle: Bundle, out: Path, s: ExportSettings, key: np.ndarray | None, verify) -> ExportResult:
    """Write ``base.onnx``, the records and ``export.json`` to ``out``, if ``verify(folder)`` passes."""
    onnx, _ = common.require_onnx()
    in_shape = tuple(bundle.manifest[C.M_IO]["input_shape"])
    batch = {0: "batch"}
    try:
        with staged_dir(out, what="export folder") as tmp:
            x0 = torch.zeros(2, *in_shape)
            module = bundle.loaded.module.eval()
            axes = {"x": batch, "y": batch}
            common.export_graph(module, (x0,), tmp / C.BASE_GRAPH, ["x"], ["y"], axes, s.opset)
            onnx.checker.check_model(str(tmp / C.BASE_GRAPH))
            copy_records(Path(bundle.path), tmp, bundle.manifest)
            meta = _meta(bundle, tmp, s.opset, s.atol)
            opened = bundle.records.open(key) if key is not None else None
            rid = opened.record_id if opened is not None else None
            user = {"id": rid, "version": opened.version} if opened is not None else None
            meta = stamp({**meta, C.M_ENROLMENTS: common.bind(meta, bundle, key, user, rid)}, C.EXPORT_DIGEST)
            (tmp / C.EXPORT_META).write_text(dump_json(meta))
            table = verify(tmp)
            if not all(r["ok"] for r in table):
                raise VerificationFailed
    except VerificationFailed:
        return ExportResult(out, s.opset, s.atol, [], table, False, meta)
    files = [C.BASE_GRAPH, C.EXPORT_META, *(r["file"] for r in bundle.manifest[C.M_RECORDS])]
    return ExportResult(out, s.opset, s.atol, files, table, True, meta)


def _meta(bundle: Bundle, folder: Path, opset: int, atol: float) -> dict:
    m = bundle.manifest
    params = common.gemm_params(folder / C.BASE_GRAPH, bundle.layer_names)
    return {
        **common.identity(m),
        "format": C.EXPORT_FORMAT,
        "mode": C.MODE_SEALED,
        "exporter": common.EXPORTER,
        "opset": opset,
        "verified_atol": atol,
        "bundle_files": dict(m[C.M_FILES]),
        "input_shape": list(m[C.M_IO]["input_shape"]),
        # What opening a record needs: the bound public fields (associated data) and the records.
        "sealed": public_part(m),
        "layers": [
            {"layer": n, "weight": params.get(n, (None, None))[0], "bias": params.get(n, (None, None))[1]}
            for n in bundle.layer_names
        ],
        "graphs": {C.BASE_GRAPH: sha256_file(folder / C.BASE_GRAPH)},
    }


def verify(
    bundle: Bundle, folder: Path, key: np.ndarray | None, x: np.ndarray, rng: np.random.Generator, atol: float
) -> list[dict]:
    """onnxruntime vs torch for a sealed export: no key, a random key and ``key`` (the user's)."""
    keys = [("null", None), ("random", rng.integers(0, 2, bundle.key_bits).astype(np.uint8))]
    if key is not None:
        keys.append(("user", np.asarray(key, np.uint8)))
    rows = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the random key opens nothing, by design
        for key_name, bits in keys:
            ref = KeyedPolicy(bundle, bits, allow_unenrolled=True)(x)
            got = SealedOnnxRunner(folder, bits, threads=1, allow_unenrolled=True,
                                   allow_rollback=bundle.mode.allow_rollback)(x)  # fmt: skip
            rows.append(common.diff_row(C.BASE_GRAPH, key_name, got, ref, atol))
    return rows


class SealedOnnxRunner:
    """A sealed bundle's export run with onnxruntime: ``base.onnx``, with the user's payload folded
    into the keyed layers' initializers in this process's memory when ``key_bits`` is bound to the
    export (``prop export --onnx --key-file``) and opens its record. A key the export does not bind is
    refused (``allow_unenrolled``: base.onnx runs, with a warning); an export or record changed since it
    was bound is refused, and so is a record older than one this machine has seen, or removed here
    (the torch path's rollback check; ``allow_rollback``: it runs, with a warning). Nothing is written
    but that check's state."""

    def __init__(
        self, folder: Path, key_bits: np.ndarray | None = None, threads: int = 0, *,
        allow_unenrolled: bool = False, allow_rollback: bool = False,
    ) -> None:  # fmt: skip
        _, ort = common.require_onnx()
        folder = Path(folder)
        self.meta = common.read_export(folder)
        check_meta(self.meta, common.require_mode(self.meta, folder, C.MODE_SEALED))
        self.opened = None
        so = common.session_options(ort, threads)
        self._keep: list = []
        if key_bits is not None:
            bits = common.key_bits(key_bits, self.meta["sealed"]["key"]["bits"])
            self.opened = _open(folder, self.meta, bits, allow_unenrolled, allow_rollback)
        if self.opened is not None:
            self._fold(folder, so, ort)
        self.session = common.open_session(ort, folder / C.BASE_GRAPH, so)

    def _fold(self, folder: Path, so, ort) -> None:
        """The opened payload folded into the keyed layers' initializers that export.json names."""
        from onnx import numpy_helper

        layers = self.meta["layers"]
        bias = self.opened.payload.spec.variant.changes_bias
        missing = [x["layer"] for x in layers if not x["weight"] or (bias and not x["bias"])]
        if missing:
            raise PropError(
                f"{folder / C.BASE_GRAPH} does not expose the weights of {', '.join(missing)} by name",
                "run the bundle with torch (prop run without --onnx)",
            )
        inits = {i.name: i for i in common.load_graph(folder / C.BASE_GRAPH).graph.initializer}
        for i, x in enumerate(layers):
            for part in ("weight", "bias") if bias else ("weight",):
                if x[part] not in inits:
                    raise PropError(
                        f"{folder / C.EXPORT_META} field 'layers[{i}].{part}' names no initializer of "
                        f"{C.BASE_GRAPH} ({quoted(x[part])})",
                        common.REEXPORT,
                    )
        try:
            with torch.no_grad():
                for x in layers:
                    w = torch.from_numpy(numpy_helper.to_array(inits[x["weight"]]).copy())
                    self._override(so, ort, x["weight"], self.opened.payload.weight(x["layer"], w))
                    if bias:
                        b = torch.from_numpy(numpy_helper.to_array(inits[x["bias"]]).copy())
                        self._override(so, ort, x["bias"], b + self.opened.payload.bias_delta(x["layer"]))
        except (RuntimeError, ValueError) as e:  # an initializer of another shape than the payload's layer
            raise PropError(
                f"{folder / C.EXPORT_META}: the payload of layer {x['layer']!r} does not fit the initializer "
                f"it names ({brief(e, 80)})",
                common.REEXPORT,
            ) from None

    def _override(self, so, ort, name: str, t) -> None:
        common.add_weight(so, ort, name, t.detach().numpy(), self._keep)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return self.session.run(["y"], {"x": np.ascontiguousarray(x, np.float32)})[0]


def check_meta(meta: dict, doc: Doc) -> None:
    """What the rules of a sealed export's fields cannot say: its public part is export.json's own
    (files, bundle id, input shape), its records have one id each, and ``layers`` names the payload's."""
    public = meta["sealed"]
    if meta[common.FORMAT] >= common.VERSIONED_SINCE:
        if public[C.M_FILES] != meta["bundle_files"]:
            raise doc.bad(f"sealed.{C.M_FILES}", "differs from bundle_files")
        if public.get(C.M_BUNDLE_ID) != meta.get(C.M_BUNDLE_ID):
            raise doc.bad(f"sealed.{C.M_BUNDLE_ID}", f"differs from {C.M_BUNDLE_ID}")
    if public[C.M_IO]["input_shape"] != meta["input_shape"]:
        raise doc.bad("sealed.io.input_shape", "differs from input_shape")
    ids = [r["id"] for r in public[C.M_RECORDS]]
    if len(set(ids)) != len(ids):
        raise doc.bad(f"sealed.{C.M_RECORDS}", "holds two records with the same id")
    if [x["layer"] for x in meta["layers"]] != [p["name"] for p in public[C.M_PAYLOAD]["layers"]]:
        raise doc.bad("layers", "must name the payload's layers, in order (sealed.payload.layers)")


def _open(folder: Path, meta: dict, bits: np.ndarray, allow_unenrolled: bool, allow_rollback: bool):
    """The record ``bits`` opens in a sealed export, checked: a PropError if the export does not bind
    the key (``allow_unenrolled``: None, with a warning), if the export, its bundle or the record
    changed since, if the record is not the one the key was bound with, or if this machine has seen
    the record removed or a newer one (``common.check_opened``; ``allow_rollback``: a warning)."""
    public = meta["sealed"]
    binding = common.bound(meta, bits, folder, public)
    if binding is None:
        common.not_bound(folder, allow_unenrolled)
        return None
    opened = load_state(folder, public).open(bits)
    user = binding.get("user") or {}
    if opened is not None and "id" in user and user["id"] != opened.record_id:
        opened.changed = [*opened.changed, "the record"]
    if opened is None or opened.changed:
        parts = opened.changed if opened is not None else ["the record"]
        raise changed_error(f"the ONNX export in {folder}", parts, common.REEXPORT)
    versioned = public.get(C.M_BUNDLE_ID) is not None
    common.check_opened(meta, folder, opened.record_id, opened.version, versioned, allow_rollback)
    return opened


def drop_record(folder: Path, record_id: str, version: int | None = None) -> None:
    """Remove a user's record, and the key binding that goes with it, from a sealed export in place.
    ``version``: the bundle version the removal writes; the export takes it if it was in step with the
    bundle (one version behind)."""
    common.refuse_link(folder, "the ONNX export", "remove the link (and export again), then retry")
    meta = common.read_export(folder)
    public = meta["sealed"]
    public[C.M_RECORDS] = [r for r in public[C.M_RECORDS] if r["id"] != record_id]
    meta[C.M_ENROLMENTS] = [e for e in meta.get(C.M_ENROLMENTS, []) if e.get("record") != record_id]
    if version is not None and meta.get(C.M_BUNDLE_VERSION) == version - 1:
        meta[C.M_BUNDLE_VERSION] = version
    record = f"{C.RECORDS_DIR}/{record_id}{C.RECORD_SUFFIX}"
    no_links(folder, record, "export")  # before anything is written
    # Through the bundle's descriptor where its lock is held (remove-user's): no link followed.
    put(folder, C.EXPORT_META, dump_json(stamp(meta, C.EXPORT_DIGEST)).encode(), "export", output=True)
    delete(folder, record, "export")


def add_record(folder: Path, bundle: Path, old: dict, manifest: dict, record_id: str) -> None:
    """Add a new user's record to a sealed export in place (as ``drop_record`` removes one): its graphs
    hold no record, so the export then serves the bundle as it is. The new key is bound to nothing
    (`prop export --onnx --key-file` binds it); the keys bound before stay bound (the behaviour they
    were bound to leaves out the records list). ``old``, ``manifest``: the bundle's before and after the
    record was added. An export that was not an unmodified export of the bundle as it was is left as it
    is (``describe_export`` says why)."""
    if Path(folder).is_symlink():
        return  # never written through (``refuse_link``); describe_export says it is not current
    try:
        meta = common.read_export(folder, old)
    except PropError:
        return
    entry = next(e for e in manifest[C.M_RECORDS] if e["id"] == record_id)
    data = read_record(Path(bundle), entry)  # the bytes its sha256 was checked on, copied
    # Through the bundle's descriptor where its lock is held (add-user's): no link followed.
    put(folder, entry["file"], data, "export")  # first: never listed, absent
    public = meta["sealed"]
    public[C.M_RECORDS] = [r for r in public[C.M_RECORDS] if r["id"] != record_id] + [entry]
    meta.update(common.identity(manifest))
    put(folder, C.EXPORT_META, dump_json(stamp(meta, C.EXPORT_DIGEST)).encode(), "export", output=True)


def run(bundle: Bundle, folder: Path, x: np.ndarray, key: np.ndarray | None, threads: int) -> np.ndarray:
    bits = None if key is None else bundle.check_key(key)
    return SealedOnnxRunner(folder, bits, threads=threads, allow_rollback=bundle.mode.allow_rollback)(x)
