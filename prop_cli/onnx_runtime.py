"""Running an ONNX export with onnxruntime: reading and checking it, and a policy for control loops.

The export is written by ``prop_cli.export`` (graph names and ``export.json`` in ``constants``).
"""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

import numpy as np

from . import constants as C
from .bundle import Bundle
from .errors import PropError, brief
from .files import sha256_file
from .keyed import key_codes
from .manifest import (
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

ONNX_EXTRA = "pip install 'prop-cli[onnx]'"
REEXPORT = "run prop export BUNDLE --onnx --force"
# What OnnxPolicy reads from export.json (the rest describes the export for people and other tools).
# Sealed exports hold base.onnx only, and no deltas.
EXPORT_FIELDS = {
    "graphs": obj({g: replace(SHA256, required=False) for g in C.GRAPHS}, min_len=1),
    "deltas": replace(list_of(obj({"input": text(), "layer": text(), "features": DIM,
                                   "base_weight": replace(text(), nullable=True)}, open=True)),
                      required=False),
}  # fmt: skip


def require_onnx():
    """(onnx, onnxruntime), or a PropError naming the extra to install."""
    try:
        import onnx
        import onnxruntime
    except ImportError as e:
        raise PropError(f"ONNX support needs the 'onnx' extra ({e.name} is not installed)", ONNX_EXTRA) from e
    return onnx, onnxruntime


def session(path: Path, threads: int = 0):
    _, ort = require_onnx()
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.log_severity_level = 3
    return open_session(ort, path, so)


def open_session(ort, path: Path, so):
    """An onnxruntime session; a graph it cannot load (damaged, edited, too new) is a PropError."""
    try:
        return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    except Exception as e:  # noqa: BLE001 - onnxruntime's own exception types (Fail, InvalidGraph, ...)
        raise PropError(f"onnxruntime cannot load {path} ({brief(e)})", REEXPORT) from None


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


class OnnxPolicy:
    """Run an export with onnxruntime, one control step per call: ``policy(x) -> y``.

    With a key, delta is computed once here (encoder.onnx). Folded (the default where the export
    names the keyed layers' weights): base.onnx runs with those weights replaced, in this process's
    memory only, by W diag(delta) (onnxruntime initializer overrides), so a step costs a base step
    (the split form measured 1.1-1.2x base.onnx: an extra Mul per keyed layer; benchmarks/table.py).
    Nothing folded is ever written. ``fold=False``: the split form, delta bound to policy.onnx.
    Without a key each call runs base.onnx. Calls go through an IOBinding, the cheapest per-call
    path at batch 1. ``threads`` = 0 lets onnxruntime choose. Not thread-safe (one binding per instance).
    """

    def __init__(
        self, folder: Path, key_code: np.ndarray | None = None, threads: int = 0, fold: bool | None = None
    ) -> None:
        _, ort = require_onnx()
        folder = Path(folder)
        self.meta = read_export(folder)
        self.names = [d["input"] for d in self.meta["deltas"]]
        self._keep: list = []  # OrtValues the session reads from must outlive it
        bound: dict = {}
        if key_code is None:
            self.session = session(folder / C.BASE_GRAPH, threads)
        else:
            code = np.asarray(key_code, np.float32).reshape(1, -1)
            deltas = session(folder / C.ENCODER_GRAPH, threads).run(self.names, {"code": code})
            if fold is None:
                fold = all(d.get("base_weight") for d in self.meta["deltas"])
            if fold:
                self.session = self._folded(folder, deltas, threads, ort)
            else:
                self.session = session(folder / C.POLICY_GRAPH, threads)
                bound = {n: ort.OrtValue.ortvalue_from_numpy(d) for n, d in zip(self.names, deltas)}
                self._keep += bound.values()
        self._binding = self.session.io_binding()
        for n, v in bound.items():
            self._binding.bind_ortvalue_input(n, v)
        self._binding.bind_output("y")
        self._rows: int | None = None  # the batch size the output binding was last run with

    def _folded(self, folder: Path, deltas: list[np.ndarray], threads: int, ort):
        onnx, _ = require_onnx()
        from onnx import numpy_helper

        weights = [d.get("base_weight") for d in self.meta["deltas"]]
        if not all(weights):
            raise PropError(
                f"{folder / C.BASE_GRAPH} does not expose the keyed layers' weights by name",
                "run without fold (the split form, policy.onnx)",
            )
        inits = {i.name: i for i in onnx.load(str(folder / C.BASE_GRAPH)).graph.initializer}
        so = ort.SessionOptions()
        so.intra_op_num_threads, so.inter_op_num_threads, so.log_severity_level = threads, 1, 3
        for name, d in zip(weights, deltas):
            w = numpy_helper.to_array(inits[name]) * d.reshape(1, -1)  # Gemm B (out, in), transB=1
            v = ort.OrtValue.ortvalue_from_numpy(np.ascontiguousarray(w, np.float32))
            self._keep.append(v)
            so.add_initializer(name, v)
        return open_session(ort, folder / C.BASE_GRAPH, so)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(x, np.float32)
        if self._rows is not None and x.shape[0] != self._rows:
            # The bound output keeps the shape of its first run: a new batch size needs a fresh one.
            self._binding.clear_binding_outputs()
            self._binding.bind_output("y")
        self._rows = x.shape[0]
        self._binding.bind_cpu_input("x", x)
        self.session.run_with_iobinding(self._binding)
        return self._binding.copy_outputs_to_cpu()[0]


def run_onnx(
    bundle: Bundle, x: np.ndarray, key: np.ndarray | None, folder: Path | None = None, threads: int = 0
) -> np.ndarray:
    """`prop run --onnx`: the bundle's outputs computed by its exported graphs (folded where possible).

    ``threads``: onnxruntime's intra-op threads (0: ``OMP_NUM_THREADS`` if set, else onnxruntime's choice)."""
    require_onnx()
    folder = Path(folder) if folder is not None else Path(bundle.path) / C.EXPORT_DIR
    if not folder.is_dir():
        raise PropError(
            f"no ONNX export at {folder}", "run prop export BUNDLE --onnx first, or pass --onnx-dir"
        )
    read_export(folder, bundle.manifest)
    threads = threads or int(os.environ.get("OMP_NUM_THREADS", "0") or 0)
    if bundle.is_sealed:
        return SealedOnnxPolicy(folder, None if key is None else bundle.check_key(key), threads=threads)(x)
    code = None
    if key is not None:
        code = key_codes(bundle.check_key(key), bundle.key_encoding).numpy()
    return OnnxPolicy(folder, code, threads=threads)(x)


class SealedOnnxPolicy:
    """A sealed bundle's export run with onnxruntime: ``base.onnx``, with the user's payload folded
    into the keyed layers' initializers in this process's memory when ``key_bits`` opens a record.
    A key that opens nothing runs the base (the original), as the bundle does; nothing is written."""

    def __init__(self, folder: Path, key_bits: np.ndarray | None = None, threads: int = 0) -> None:
        import torch

        from .sealed import load_state

        onnx, ort = require_onnx()
        folder = Path(folder)
        self.meta = read_export(folder)
        self.opened = None
        so = ort.SessionOptions()
        so.intra_op_num_threads, so.inter_op_num_threads, so.log_severity_level = threads, 1, 3
        self._keep: list = []
        if key_bits is not None:
            self.opened = load_state(folder, self.meta["sealed"]).open(np.asarray(key_bits, np.uint8))
        if self.opened is not None:
            from onnx import numpy_helper

            missing = [x["layer"] for x in self.meta["layers"] if not x["weight"]]
            full = self.opened.payload.spec.kind == "full"
            missing += [x["layer"] for x in self.meta["layers"] if full and x["weight"] and not x["bias"]]
            if missing:
                raise PropError(
                    f"{folder / C.BASE_GRAPH} does not expose the weights of {', '.join(missing)} by name",
                    "run the bundle with torch (prop run without --onnx)",
                )
            inits = {i.name: i for i in onnx.load(str(folder / C.BASE_GRAPH)).graph.initializer}
            with torch.no_grad():
                for x in self.meta["layers"]:
                    w = torch.from_numpy(numpy_helper.to_array(inits[x["weight"]]).copy())
                    self._override(so, ort, x["weight"], self.opened.payload.weight(x["layer"], w))
                    if full:
                        b = torch.from_numpy(numpy_helper.to_array(inits[x["bias"]]).copy())
                        self._override(
                            so, ort, x["bias"], b + self.opened.payload.tensor(x["layer"], "bias_delta")
                        )
        self.session = ort.InferenceSession(
            str(folder / C.BASE_GRAPH), so, providers=["CPUExecutionProvider"]
        )

    def _override(self, so, ort, name: str, t) -> None:
        v = ort.OrtValue.ortvalue_from_numpy(np.ascontiguousarray(t.detach().numpy(), np.float32))
        self._keep.append(v)  # must outlive the session
        so.add_initializer(name, v)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return self.session.run(["y"], {"x": np.ascontiguousarray(x, np.float32)})[0]
