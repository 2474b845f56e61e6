"""What both export modes share: onnx/onnxruntime on demand, tracing one graph, reading and checking an
export's ``export.json``, and comparing onnxruntime with torch."""

from __future__ import annotations

import hashlib
import inspect
import itertools
import os
import re
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from prop_cli import constants as C
from prop_cli.bundle import Bundle, rollback
from prop_cli.bundle.enrol import (
    BUNDLE_ID,
    FILE,
    behaviour,
    changed,
    changed_error,
    enrolment,
    open_enrolment,
)
from prop_cli.bundle.manifest import (
    INPUT_SHAPE,
    NAME,
    SCHEMA,
    Doc,
    canonical_json,
    check_digest,
    check_fields,
    check_version,
    read_json,
)
from prop_cli.config import ExportSettings
from prop_cli.core.rules import DIM, SHA256, choice, hex_string, integer, list_of, number, obj, optional, text
from prop_cli.errors import PropError, brief
from prop_cli.files import no_links, read, sha256_inside

from ..streams import stdout_to_stderr

ONNX_EXTRA = "pip install 'prop-keys[onnx]'"
REEXPORT = "run prop export BUNDLE --onnx --force"
VERIFY_BATCH = 16
EXPORTER = f"torch {torch.__version__} (TorchScript-based, dynamo=False)"
FORMAT = "format"
VERSIONED_SINCE = 4  # export format 4: the bundle's id and version, the key's record bound (issue 42)
MAX_META = 64 << 20  # the largest export.json read: a sealed export of 65536 records is ~20 MB
WHAT = "ONNX export"  # how link errors name an export folder
# export.json, field by field, as the bundle manifest's SCHEMA: each typed and bounded, unknown fields
# refused, every path a fixed name inside the export folder (graphs) or users/<file name> (records).
# Required per mode: "unsealed" (four graphs, an encoder), "sealed" (base.onnx and the records).
UNSEALED, SEALED = (C.MODE_UNSEALED,), (C.MODE_SEALED,)
ENROLMENT = obj({
    "salt": hex_string(16, 16), "nonce": hex_string(12, 12), "box": hex_string(16, 1 << 16),
    "record": optional(text()),
})  # fmt: skip
# What opening a record needs: the bundle manifest's public fields (``records.public_part``), by its rules.
SEALED_PART = {
    **{f: SCHEMA[f] for f in (C.M_FORMAT, C.M_MODEL, C.M_TASK, C.M_IO, C.M_KEY, C.M_FILES, C.M_BUNDLE_ID)},
    C.M_MODE: choice(SEALED),
    C.M_PAYLOAD: optional(SCHEMA[C.M_PAYLOAD], True),
    C.M_RECORDS: optional(SCHEMA[C.M_RECORDS], True),
    C.M_KEYED_LAYERS: optional(SCHEMA[C.M_KEYED_LAYERS], nullable=True),
}
EXPORT_FIELDS = {
    FORMAT: integer(min(C.EXPORT_FORMATS), max(C.EXPORT_FORMATS)),
    C.M_MODE: optional(choice(C.MODES)),
    "exporter": text(),
    "opset": integer(1, 64),
    "verified_atol": number(0, 1e6, open_lo=True),
    "bundle_files": SCHEMA[C.M_FILES],
    "input_shape": INPUT_SHAPE,
    C.M_BUNDLE_ID: SCHEMA[C.M_BUNDLE_ID],
    C.M_BUNDLE_VERSION: SCHEMA[C.M_BUNDLE_VERSION],
    "graphs": obj({g: optional(SHA256) for g in C.GRAPHS}, min_len=1),
    C.M_ENROLMENTS: optional(list_of(ENROLMENT)),
    # Unsealed: the key's layout and the encoder's outputs, one scale per keyed layer.
    "key": optional(obj({"bits": SCHEMA[C.M_KEY].fields["bits"], "encoding": choice(C.KEY_ENCODINGS)}),
                    UNSEALED),
    "code": optional(text()),
    "deltas": optional(list_of(obj({"input": text(), "layer": NAME, "features": DIM,
                                    "base_weight": optional(text(), nullable=True)}), 1), UNSEALED),
    # Sealed: the public fields, and the initializers the payload of each keyed layer folds into.
    "sealed": optional(obj(SEALED_PART), SEALED),
    "layers": optional(list_of(obj({"layer": NAME, "weight": optional(text(), True, nullable=True),
                                    "bias": optional(text(), True, nullable=True)}), 1), SEALED),
}  # fmt: skip
# What a runtime reads of export.json besides the graphs: bound to each key with them (``bind``).
FEEDS = ("input_shape", "key", "deltas", "layers")
# torch >= 2.5 takes `dynamo`; older versions only have the TorchScript exporter.
_LEGACY_EXPORTER = {"dynamo": False} if "dynamo" in inspect.signature(torch.onnx.export).parameters else {}


class VerificationFailed(Exception):
    """onnxruntime and torch differ by more than atol: nothing is written."""


@dataclass
class ExportResult:
    out: Path
    opset: int
    atol: float
    files: list[str]
    table: list[dict]  # one row per (graph, key): max_abs, max_rel, ok
    ok: bool
    meta: dict = field(repr=False, default_factory=dict)


def require_onnx():
    """(onnx, onnxruntime), or a PropError naming the extra to install."""
    try:
        import onnx
        import onnxruntime
    except ImportError as e:
        raise PropError(f"ONNX support needs the 'onnx' extra ({e.name} is not installed)", ONNX_EXTRA) from e
    return onnx, onnxruntime


def session_options(ort, threads: int):
    so = ort.SessionOptions()
    so.intra_op_num_threads, so.inter_op_num_threads, so.log_severity_level = threads, 1, 3
    return so


def add_weight(so, ort, name: str, w: np.ndarray, keep: list) -> None:
    """Replace initializer ``name`` by ``w`` in the session ``so`` opens. A convolution's weight (ndim > 2)
    limits the session to extended optimizations: at the full level onnxruntime (1.32) pre-packs Conv
    weights for its NCHWc layout from the file's initializer and ignores the replacement (measured: a
    zeroed Conv weight changed nothing)."""
    v = ort.OrtValue.ortvalue_from_numpy(np.ascontiguousarray(w, np.float32))
    keep.append(v)  # must outlive the session
    so.add_initializer(name, v)
    if w.ndim > 2:
        so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED


def session(path: Path, threads: int = 0):
    _, ort = require_onnx()
    return open_session(ort, path, session_options(ort, threads))


def load_graph(path: Path):
    """``path``'s ONNX model, parsed without reading anything beside it, and refused in one line if any
    of its tensors keeps its data in another file (``check_no_external_data``)."""
    onnx, _ = require_onnx()
    try:
        model = onnx.load(str(path), load_external_data=False)
    except Exception as e:  # noqa: BLE001 - protobuf's DecodeError, OSError, onnx's own checks
        raise PropError(f"{path} is not a readable ONNX graph ({brief(e)})", REEXPORT) from None
    check_no_external_data(model, path)
    return model


def _tensors(graph) -> Iterator:
    """Every tensor a graph holds: initializers, sparse ones, and node attributes, subgraphs included."""
    yield from graph.initializer
    for sparse in graph.sparse_initializer:
        yield from (sparse.values, sparse.indices)
    for node in graph.node:
        yield from _attribute_tensors(node)


def _attribute_tensors(node) -> Iterator:
    for a in node.attribute:
        if a.HasField("t"):
            yield a.t
        yield from a.tensors
        if a.HasField("sparse_tensor"):
            yield from (a.sparse_tensor.values, a.sparse_tensor.indices)
        for sub in [a.g] * a.HasField("g") + list(a.graphs):
            yield from _tensors(sub)


def check_no_external_data(model, path: Path) -> None:
    """prop writes every tensor inside its graph file, hashed in export.json: a tensor whose data lives
    in another file (``external_data``: a location that may be outside the folder, absolute, or of any
    length) is refused before onnx or onnxruntime would read that file."""
    from onnx import TensorProto

    functions = [n for f in model.functions for n in f.node]
    tensors = itertools.chain(_tensors(model.graph), *(_attribute_tensors(n) for n in functions))
    for t in tensors:
        if t.data_location == TensorProto.EXTERNAL or len(t.external_data):
            where = next((e.value for e in t.external_data if e.key == "location"), "?")
            raise PropError(
                f"{path}: tensor {t.name[:80]!r} keeps its data in another file ({where[:120]!r}); prop "
                "writes every tensor inside the graph and reads nothing beside it",
                REEXPORT,
            )


def open_session(ort, path: Path, so):
    """An onnxruntime session; a graph it cannot load (damaged, edited, too new, or keeping data in
    another file: ``load_graph``) is a PropError."""
    load_graph(path)
    try:
        return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    except Exception as e:  # noqa: BLE001 - onnxruntime's own exception types (Fail, InvalidGraph, ...)
        raise PropError(f"onnxruntime cannot load {path} ({brief(e)})", REEXPORT) from None


def refuse_link(folder: Path, what: str, fix: str) -> None:
    """prop never writes or deletes through a symbolic link: an export folder that is one (a bundle's
    onnx/ pointing somewhere else) is refused, not followed."""
    folder = Path(folder)
    if folder.is_symlink():
        raise PropError(
            f"{what} {folder} is a symbolic link (to {os.readlink(folder)}): prop never writes or deletes "
            "through one",
            fix,
        )


def read_export(folder: Path, bundle_manifest: dict | None = None) -> dict:
    """Read and check ``export.json`` as the bundle manifest is read: its size, JSON, format version,
    digest and schema (``EXPORT_FIELDS``, every field typed and bounded, unknown ones refused), how its
    fields fit together, no link on any path read, and the graphs' hashes; with a manifest, that it is
    an export of that bundle as it is (``check_current``). One-line PropErrors naming the field."""
    folder = Path(folder)
    mpath = no_links(folder, C.EXPORT_META, WHAT)
    if not mpath.is_file():
        raise PropError(
            f"{folder} holds no ONNX export ({C.EXPORT_META} missing)", "run prop export BUNDLE --onnx"
        )
    doc = Doc(str(mpath), fix=REEXPORT)
    try:  # from the folder's descriptor (its bundle's, under the bundle's lock): no link below followed
        raw = read(folder, C.EXPORT_META, WHAT, limit=MAX_META + 1)
    except OSError as e:
        raise PropError(f"{mpath} cannot be read ({e.strerror})", "check its permissions") from None
    if len(raw) > MAX_META:
        raise PropError(f"{mpath} is over {MAX_META >> 20} MiB, more than prop ever writes", REEXPORT)
    meta = read_json(raw, str(mpath), REEXPORT)
    if check_version(meta, FORMAT, C.EXPORT_FORMATS, doc) >= 2 or C.EXPORT_DIGEST in meta:
        check_digest(meta, raw, C.EXPORT_DIGEST, doc)
    doc = doc_of(folder, meta)
    check_fields(EXPORT_FIELDS, {k: v for k, v in meta.items() if k != C.EXPORT_DIGEST}, doc)
    _cross_check(meta, doc)
    for g, digest in meta["graphs"].items():
        path = no_links(folder, g, WHAT)
        try:
            same = sha256_inside(folder, g, WHAT) == digest
        except OSError:
            same = False
        if not same:
            raise PropError(f"{path} is missing or modified", REEXPORT)
    for entry in (meta.get("sealed") or {}).get(C.M_RECORDS, []):
        no_links(folder, entry["file"], WHAT)  # users/ linked elsewhere: refused, not followed
    if bundle_manifest is not None:
        check_current(meta, folder, bundle_manifest)
    return meta


# Each mode's own fields and graphs: an export holds those of its mode only.
OWN_FIELDS = {C.MODE_UNSEALED: ("key", "code", "deltas"), C.MODE_SEALED: ("sealed", "layers")}
OWN_GRAPHS = {C.MODE_UNSEALED: set(C.GRAPHS), C.MODE_SEALED: {C.BASE_GRAPH}}
RUNNERS = {C.MODE_UNSEALED: "OnnxRunner", C.MODE_SEALED: "SealedOnnxRunner"}


def _cross_check(meta: dict, doc: Doc) -> None:
    """What one field's rule cannot say: how export.json's fields fit together (each mode's own checks:
    ``sealed.check_meta``, ``unsealed.check_meta``, which its runner calls)."""
    for mode, names in OWN_FIELDS.items():
        for name in names:
            if name in meta and mode != doc.mode:
                raise doc.bad(name, f"is not a field of {doc.mode} exports")
    want = OWN_GRAPHS[doc.mode]
    if set(meta["graphs"]) != want:
        found = ", ".join(sorted(meta["graphs"]))
        raise doc.bad("graphs", f"must name {', '.join(sorted(want))} (found {found})")
    if meta[FORMAT] >= VERSIONED_SINCE and (C.M_BUNDLE_ID in meta) != (C.M_BUNDLE_VERSION in meta):
        missing = C.M_BUNDLE_VERSION if C.M_BUNDLE_ID in meta else C.M_BUNDLE_ID
        raise doc.bad(missing, "is missing (an export of a versioned bundle carries its id and version)")


def doc_of(folder: Path, meta: dict) -> Doc:
    """How errors name export.json in ``folder`` and the field they are about, in its mode."""
    mode = meta.get(C.M_MODE)
    return Doc(str(Path(folder) / C.EXPORT_META), mode if mode in C.MODES else C.MODE_UNSEALED, REEXPORT)


def require_mode(meta: dict, folder: Path, mode: str) -> Doc:
    """``meta`` is the export of a bundle of ``mode`` (each mode has its runner); its Doc."""
    doc = doc_of(folder, meta)
    if doc.mode != mode:
        raise PropError(
            f"{folder} is the ONNX export of a {doc.mode} bundle", f"run it with {RUNNERS[doc.mode]}"
        )
    return doc


def check_current(meta: dict, folder: Path, manifest: dict) -> None:
    """``meta`` is the export of the bundle ``manifest`` describes as it is now: made from its files,
    its id and version (prop keeps the export in ``<bundle>/onnx`` in step with every write), and for a
    sealed bundle holding its records; else a PropError saying which."""
    where = f"the ONNX export in {folder}"
    other_id = C.M_BUNDLE_ID in meta and meta[C.M_BUNDLE_ID] != manifest.get(C.M_BUNDLE_ID)
    if meta.get("bundle_files") != manifest.get(C.M_FILES) or other_id:
        raise PropError(f"{where} was made from another bundle (or an older version of it)", REEXPORT)
    have, want = meta.get(C.M_BUNDLE_VERSION), manifest.get(C.M_BUNDLE_VERSION)
    if have != want:
        if have is None:
            why = f"by an older prop (export format {meta[FORMAT]}), without the bundle's version"
        else:
            older = "an older" if have < want else "another"
            why = f"from {older} version of the bundle (version {have}; the bundle is at version {want})"
        raise PropError(f"{where} was made {why}", REEXPORT)
    public = meta.get("sealed") or {}
    if public.get(C.M_RECORDS) != manifest.get(C.M_RECORDS):
        raise PropError(f"{where} holds other user records than the bundle", REEXPORT)


def identity(manifest: dict) -> dict:
    """export.json's copy of the bundle's id and version (format 5 bundles; others have none)."""
    return {k: manifest[k] for k in (C.M_BUNDLE_ID, C.M_BUNDLE_VERSION) if k in manifest}


def feeds(meta: dict) -> str:
    """The digest of what a runtime reads of export.json besides the graphs (``FEEDS``)."""
    return hashlib.sha256(canonical_json({f: meta.get(f) for f in FEEDS})).hexdigest()


def bind(
    meta: dict, bundle: Bundle, key: np.ndarray | None, user: dict | None = None, record: str | None = None
) -> list[dict]:
    """export.json's enrolments: ``key`` (if given) bound to these graphs and this bundle, so that the
    key runs only them (``bound``). The key must be enrolled in the bundle as it is now. Bound with it,
    under the key: what the runtimes read of export.json (``feeds``), and ``user``: the record or
    enrolment the key opens ({"id", "version"}: its id and the bundle version it was written in), which
    the runners check against this machine's rollback state (``check_opened``). ``record``: the sealed
    record the key opens (public), so that remove-user --record drops the binding with it."""
    if key is None:
        return []
    if not bundle.mode.enrolled(key):
        raise PropError(
            f"the key is enrolled in no user of {bundle.path}: there is no behaviour of it to export",
            "pass the key of one of the bundle's users, or export without --key-file",
        )
    what = {"bundle": behaviour(bundle.manifest), "graphs": meta["graphs"], "feeds": feeds(meta)}
    what["user"] = user or {"id": None, "version": 0}
    return [{**enrolment(key, what), **({"record": record} if record else {})}]


def bound(meta: dict, bits: np.ndarray, folder: Path, manifest: dict | None = None) -> dict | None:
    """What binds ``bits`` to this export's graphs as they are (the binding's plaintext), None where it
    is bound to nothing, or a PropError where it is bound to graphs, fields or a bundle that changed
    since (nothing runs). ``manifest``: the bundle's, to check against it too (else against the bundle
    files and id export.json names)."""
    opened = open_enrolment(meta.get(C.M_ENROLMENTS, []), bits)
    if opened is None:
        return None
    graphs = {FILE + g: d for g, d in meta["graphs"].items()}
    diff = changed({FILE + g: d for g, d in opened.get("graphs", {}).items()}, graphs)
    if meta[FORMAT] >= VERSIONED_SINCE and (opened.get("feeds") != feeds(meta) or "user" not in opened):
        diff.append(C.EXPORT_META)
    enrolled = opened.get("bundle", {})
    if manifest is not None:
        diff += changed(enrolled, behaviour(manifest))
    else:
        files = {FILE + f: d for f, d in (meta.get("bundle_files") or {}).items()}
        bundle_id = meta.get(C.M_BUNDLE_ID, (meta.get("sealed") or {}).get(C.M_BUNDLE_ID))
        if bundle_id is not None:
            files[BUNDLE_ID] = behaviour_entry(bundle_id)
        diff += changed({k: v for k, v in enrolled.items() if k.startswith(FILE) or k == BUNDLE_ID}, files)
    if diff:
        raise changed_error(f"the ONNX export in {folder}", diff, REEXPORT)
    return opened


def behaviour_entry(value: object) -> str:
    """A value as a behaviour entry holds it (``enrol.behaviour``: the sha256 of its canonical JSON)."""
    return hashlib.sha256(canonical_json(value)).hexdigest()


def check_opened(
    meta: dict, folder: Path, uid: str | None, version: int, versioned: bool, allow: bool
) -> None:
    """The rollback check the torch path runs (``bundle.rollback.opened``), on what a runner of this
    export opened with a key: record or enrolment ``uid`` written at bundle ``version``, in the export
    of the bundle version export.json names. ``versioned``: the record or binding belongs to a bundle
    with an id (format 5), whose export must carry its version (export format 4 on). ``allow``:
    --allow-rollback (a warning instead of the refusal)."""
    where = f"the ONNX export in {folder}"
    if meta[FORMAT] < VERSIONED_SINCE:
        if versioned:
            raise PropError(
                f"{where} was made by an older prop (export format {meta[FORMAT]}): it does not carry the "
                "bundle version the rollback check needs",
                REEXPORT,
            )
        return
    if C.M_BUNDLE_ID not in meta:
        return  # a format 1-4 bundle: no version, nothing remembered (as with torch)
    seen_as = {C.M_BUNDLE_ID: meta[C.M_BUNDLE_ID], C.M_BUNDLE_VERSION: meta[C.M_BUNDLE_VERSION]}
    rollback.opened(seen_as, uid, version, where, allow)


def key_bits(key, bits: int) -> np.ndarray:
    """Key bits (0/1) of the size the export takes; a ±1 code or another size is refused."""
    k = np.asarray(key)
    if k.ndim != 1 or len(k) != bits or not np.isin(k, (0, 1)).all():
        raise PropError(
            f"the key must be {bits} bits of 0/1 (read_key_file), got shape {k.shape}",
            "pass the key bits; an encoder code goes to code= (unchecked)",
        )
    return k.astype(np.uint8)


def not_bound(folder: Path, allow: bool) -> None:
    """A key the export binds to nothing: refused, or with ``allow`` base.onnx runs, with a warning
    (``run.policy.key_opens_nothing``, the one decision for a key that opens nothing)."""
    from prop_cli.run.policy import key_opens_nothing

    why = (
        f"the key is not bound to the ONNX export in {folder}; the export may have been replaced, or "
        "made without this key (prop export --onnx --key-file binds it)"
    )
    key_opens_nothing(why, allow, "running its base.onnx, not a keyed behaviour", stacklevel=4)


def export_graph(module, args, path: Path, inputs, outputs, axes, opset: int) -> None:
    """Trace ``module`` to ``path`` with torch's TorchScript-based exporter (``dynamo=False``: no extra
    package, works offline, supports ``dynamic_axes``); a failure names the operation in one line."""
    try:
        # On failure the exporter prints its IR graph to stdout, where our results go: divert it.
        with warnings.catch_warnings(), torch.no_grad(), stdout_to_stderr():
            # The legacy exporter warns that it is legacy, on every call; we chose it knowingly.
            warnings.simplefilter("ignore")
            torch.onnx.export(
                module,
                args,
                str(path),
                input_names=inputs,
                output_names=outputs,
                dynamic_axes=axes,
                opset_version=opset,
                do_constant_folding=True,
                **_LEGACY_EXPORTER,
            )
    except Exception as e:
        msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        op = re.search(r"'((?:aten|prim|onnx)::\w+)'", str(e))
        what = f"operation {op.group(1)}" if op else type(e).__name__
        raise PropError(
            f"cannot export {path.name} to ONNX opset {opset}: {what} failed ({msg[:200]})",
            f"try another --opset ({ExportSettings.MIN_OPSET}..{ExportSettings.MAX_OPSET}), "
            "or replace that operation in the model",
        ) from e


def verify_inputs(bundle: Bundle, inputs: np.ndarray | None, rng: np.random.Generator) -> np.ndarray:
    """The inputs verification runs on: the given ones (up to 64), or random ones of the bundle's shape."""
    if inputs is not None:
        return np.ascontiguousarray(inputs[:64], dtype=np.float32)
    in_shape = tuple(bundle.manifest[C.M_IO]["input_shape"])
    return rng.standard_normal((VERIFY_BATCH, *in_shape)).astype(np.float32)


def diff_row(graph: str, key: str, got: np.ndarray, ref: np.ndarray, atol: float) -> dict:
    """One verification row: max abs difference, and the same relative to the largest reference value."""
    got, ref = np.asarray(got).astype(np.float64), np.asarray(ref).astype(np.float64)
    d = float(np.max(np.abs(got - ref))) if ref.size else 0.0
    scale = float(np.max(np.abs(ref))) if ref.size else 0.0
    return {"graph": graph, "key": key, "max_abs": d, "max_rel": d / max(scale, 1e-12), "ok": bool(d <= atol)}


def gemm_params(path: Path, layers: list[str]) -> dict[str, tuple[str, str | None]]:
    """Keyed layer -> (weight, bias) initializers in ``path`` where the layer is a Gemm with transB=1 (or a
    Conv) whose initializers nothing else uses: only then is W diag(delta) a scaling of that weight's
    input columns (channels), and the layer's weights can be replaced in memory (a weight used
    elsewhere, shared or tied, cannot be scaled for this layer alone)."""
    graph = load_graph(path).graph
    inits = {i.name for i in graph.initializer}
    uses: dict[str, int] = {}
    for node in graph.node:
        for name in node.input:
            uses[name] = uses.get(name, 0) + 1
    found: dict[str, tuple[str, str | None]] = {}
    for node in graph.node:
        attrs = {a.name: a.i for a in node.attribute}
        gemm = node.op_type == "Gemm" and attrs.get("transB") == 1
        if not (gemm or node.op_type == "Conv") or len(node.input) < 2:
            continue
        w = node.input[1]
        bias = node.input[2] if len(node.input) > 2 and node.input[2] in inits else None
        if w in inits and uses.get(w) == 1 and w.endswith(".weight") and w[: -len(".weight")] in layers:
            found[w[: -len(".weight")]] = (w, bias if bias and uses.get(bias) == 1 else None)
    return found
