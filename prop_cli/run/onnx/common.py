"""What both export modes share: onnx/onnxruntime on demand, tracing one graph, reading and checking an
export's ``export.json``, and comparing onnxruntime with torch."""

from __future__ import annotations

import inspect
import itertools
import os
import re
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from prop_cli import constants as C
from prop_cli.bundle import Bundle
from prop_cli.bundle.enrol import FILE, behaviour, changed, changed_error, enrolment, open_enrolment
from prop_cli.bundle.manifest import (
    DIM,
    SHA256,
    Doc,
    check_digest,
    check_fields,
    check_version,
    list_of,
    obj,
    read_json,
    text,
)
from prop_cli.config import ExportSettings
from prop_cli.errors import PropError, brief
from prop_cli.files import sha256_file

from ..streams import stdout_to_stderr

ONNX_EXTRA = "pip install 'prop-keys[onnx]'"
REEXPORT = "run prop export BUNDLE --onnx --force"
VERIFY_BATCH = 16
EXPORTER = f"torch {torch.__version__} (TorchScript-based, dynamo=False)"
# What the runtimes read from export.json (the rest describes the export for people and other tools).
# Sealed exports hold base.onnx only, and no deltas.
EXPORT_FIELDS = {
    "graphs": obj({g: replace(SHA256, required=False) for g in C.GRAPHS}, min_len=1),
    "deltas": replace(list_of(obj({"input": text(), "layer": text(), "features": DIM,
                                   "base_weight": replace(text(), nullable=True)}, open=True)),
                      required=False),
    C.M_ENROLMENTS: replace(list_of(obj({"salt": text(), "nonce": text(), "box": text(1 << 21)}, open=True)),
                            required=False),
}  # fmt: skip
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
    """Read and check ``export.json`` (graph hashes; with a manifest, that it matches the bundle)."""
    folder = Path(folder)
    mpath = folder / C.EXPORT_META
    if not mpath.is_file():
        raise PropError(
            f"{folder} holds no ONNX export ({C.EXPORT_META} missing)", "run prop export BUNDLE --onnx"
        )
    doc = Doc(str(mpath), fix=REEXPORT)
    try:
        raw = mpath.read_bytes()
    except OSError as e:
        raise PropError(f"{mpath} cannot be read ({e.strerror})", "check its permissions") from None
    meta = read_json(raw, str(mpath), REEXPORT)
    if check_version(meta, "format", C.EXPORT_FORMATS, doc) >= 2 or C.EXPORT_DIGEST in meta:
        check_digest(meta, raw, C.EXPORT_DIGEST, doc)
    check_fields(EXPORT_FIELDS, meta, doc, open_=True)
    graphs = meta["graphs"]
    for g, digest in graphs.items():
        if not (folder / g).is_file() or sha256_file(folder / g) != digest:
            raise PropError(f"{folder / g} is missing or modified", REEXPORT)
    if bundle_manifest is not None and meta.get("bundle_files") != bundle_manifest.get(C.M_FILES):
        raise PropError(
            f"the ONNX export in {folder} was made from another bundle (or an older version of it)",
            "run prop export BUNDLE --onnx --force",
        )
    return meta


def bind(meta: dict, bundle: Bundle, key: np.ndarray | None, record: str | None = None) -> list[dict]:
    """export.json's enrolments: ``key`` (if given) bound to these graphs and this bundle, so that the
    key runs only them (``bound``). The key must be enrolled in the bundle as it is now. ``record``: the
    sealed record the key opens (public), so that remove-user --record drops the binding with it."""
    if key is None:
        return []
    if not bundle.mode.enrolled(key):
        raise PropError(
            f"the key is enrolled in no user of {bundle.path}: there is no behaviour of it to export",
            "pass the key of one of the bundle's users, or export without --key-file",
        )
    what = {"bundle": behaviour(bundle.manifest), "graphs": meta["graphs"]}
    return [{**enrolment(key, what), **({"record": record} if record else {})}]


def bound(meta: dict, bits: np.ndarray, folder: Path, manifest: dict | None = None) -> bool:
    """Whether ``bits`` is bound to this export's graphs as they are (True), bound to nothing (False),
    or bound to graphs or a bundle that changed since (a PropError: nothing runs). ``manifest``: the
    bundle's, to check against it too (else against the bundle files export.json names)."""
    opened = open_enrolment(meta.get(C.M_ENROLMENTS, []), bits)
    if opened is None:
        return False
    graphs = {FILE + g: d for g, d in meta["graphs"].items()}
    diff = changed({FILE + g: d for g, d in opened.get("graphs", {}).items()}, graphs)
    if manifest is not None:
        diff += changed(opened.get("bundle", {}), behaviour(manifest))
    else:
        files = {FILE + f: d for f, d in (meta.get("bundle_files") or {}).items()}
        diff += changed({k: v for k, v in opened.get("bundle", {}).items() if k.startswith(FILE)}, files)
    if diff:
        raise changed_error(f"the ONNX export in {folder}", diff, REEXPORT)
    return True


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
