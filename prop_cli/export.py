"""ONNX export of a bundle: tracing the graphs, checking them with onnxruntime, describing them.

Four graphs are written (names in ``constants.GRAPHS``):

- ``base.onnx``     x -> y: what the base weights compute with no key (a drop-in for the original).
- ``keyed.onnx``    (x, code) -> y with the key encoder inside the graph.
- ``encoder.onnx``  code -> delta_1..delta_L, one scale vector per keyed layer.
- ``policy.onnx``   (x, delta_1..delta_L) -> y: a control loop computes delta once per session with
  ``encoder.onnx``, then each step costs a base step plus one multiply per keyed layer.

The key input is the encoder's ±1 *code*, not the key bits: the default "hashed" encoding is
SHAKE-256 of the bits, which ONNX cannot express. The runtime computes the code with
:func:`prop_cli.keyed.key_codes` (or the three-line hashlib recipe in the README). Running an export
is ``prop_cli.onnx_runtime``.

No graph holds key material or weights folded with a key: the key enters only as a graph input at
run time, and the graphs are traced with placeholder inputs (zeros, a code of ones, deltas of ones).

Exporter: torch's TorchScript-based exporter (``dynamo=False``). It needs no extra package
(the torch.export-based one needs onnxscript), works offline and supports ``dynamic_axes``.
"""

from __future__ import annotations

import contextlib
import inspect
import os
import re
import sys
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn

from . import constants as C
from .bundle import Bundle
from .config import ExportSettings
from .errors import PropError
from .files import check_output, dump_json, sha256_file, staged_dir
from .keyed import key_codes
from .manifest import stamp
from .onnx_runtime import require_onnx, session

VERIFY_BATCH = 16


class _VerificationFailed(Exception):
    """onnxruntime and torch differ by more than atol: nothing is written."""


def delta_names(n_layers: int) -> list[str]:
    return [f"delta_{i + 1}" for i in range(n_layers)]


class DeltaPolicy(nn.Module):
    """Export-only view of the keyed model: ``(x, delta_1..delta_L) -> y``.

    Pre-hooks on the keyed layers multiply the layer input by a delta given as a graph input,
    shape (1, d_i), broadcast over the batch (and any middle axes). This is Eq. 5's
    W diag(delta) z without KeyedModel's row-gathering state, which does not trace to ONNX.
    Use as a context manager: the hooks are removed from the bundle's module on exit.
    """

    def __init__(self, module: nn.Module, layer_names: list[str]) -> None:
        super().__init__()
        self.module = module
        self._deltas: tuple[torch.Tensor, ...] | None = None
        mods = dict(module.named_modules())
        self._handles = [
            mods[name].register_forward_pre_hook(self._hook(i)) for i, name in enumerate(layer_names)
        ]

    def _hook(self, i: int):
        def pre(mod: nn.Module, args: tuple):
            if self._deltas is None:
                return None
            return (args[0] * self._deltas[i], *args[1:])

        return pre

    def forward(self, x: torch.Tensor, *deltas: torch.Tensor) -> torch.Tensor:
        self._deltas = deltas
        try:
            return self.module(x)
        finally:
            self._deltas = None

    def __enter__(self) -> DeltaPolicy:
        return self

    def __exit__(self, *exc) -> None:
        for h in self._handles:
            h.remove()


class _KeyedGraph(nn.Module):
    """(x, code) -> y: the encoder feeding the delta policy."""

    def __init__(self, encoder: nn.Module, policy: DeltaPolicy) -> None:
        super().__init__()
        self.encoder, self.policy = encoder, policy

    def forward(self, x: torch.Tensor, code: torch.Tensor) -> torch.Tensor:
        return self.policy(x, *self.encoder(code))


class _EncoderGraph(nn.Module):
    def __init__(self, encoder: nn.Module) -> None:
        super().__init__()
        self.encoder = encoder

    def forward(self, code: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return tuple(self.encoder(code))


@dataclass
class ExportResult:
    out: Path
    opset: int
    atol: float
    files: list[str]
    table: list[dict]  # one row per (graph, key): max_abs, max_rel, ok
    ok: bool
    meta: dict = field(repr=False, default_factory=dict)


def export_onnx(
    bundle: Bundle,
    out: Path | None = None,
    settings: ExportSettings | None = None,
    *,
    key: np.ndarray | None = None,
    inputs: np.ndarray | None = None,
    force: bool = False,
) -> ExportResult:
    """Write the four graphs to ``out`` (default ``<bundle>/onnx``) and verify them with onnxruntime.

    Verification compares onnxruntime with torch for the null key, a random key and ``key`` (the
    user's, if given) on ``inputs`` (or random inputs of the bundle's input shape). Files are
    written to a temporary folder and renamed into place only if every difference is <= ``atol``;
    otherwise nothing is left behind and ``ok`` is False.
    """
    s = (settings or ExportSettings()).validate()
    onnx, _ = require_onnx()
    if key is not None:
        bundle.check_key(key)
    out = Path(out) if out is not None else Path(bundle.path) / C.EXPORT_DIR
    check_output(out, force, what="export folder")
    if bundle.is_sealed:
        return _export_sealed(bundle, out, s, key, inputs)
    km = bundle.keyed.eval()
    names = delta_names(len(km.layer_names))
    in_shape = tuple(bundle.manifest[C.M_IO]["input_shape"])

    try:
        with staged_dir(out, what="export folder") as tmp:
            _export_all(km, tmp, in_shape, names, s.opset)
            for g in C.GRAPHS:
                onnx.checker.check_model(str(tmp / g))
            table = verify_graphs(bundle, tmp, key=key, inputs=inputs, seed=s.seed, atol=s.atol)
            meta = _export_meta(bundle, tmp, names, s.opset, s.atol)
            if not all(r["ok"] for r in table):
                raise _VerificationFailed  # staged_dir removes the folder: nothing is left behind
            meta = stamp(meta, C.EXPORT_DIGEST)
            (tmp / C.EXPORT_META).write_text(dump_json(meta))
    except _VerificationFailed:
        return ExportResult(out, s.opset, s.atol, [], table, False, meta)
    return ExportResult(out, s.opset, s.atol, [*C.GRAPHS, C.EXPORT_META], table, True, meta)


def _export_sealed(
    bundle: Bundle, out: Path, s: ExportSettings, key: np.ndarray | None, inputs: np.ndarray | None
) -> ExportResult:
    """A sealed bundle exports as ``base.onnx`` (the original) plus its encrypted records: the runtime
    (``onnx_runtime.SealedOnnxPolicy``) opens the user's record with their key and folds the payload
    into the keyed layers' initializers in memory. No graph holds a payload in the clear."""
    from .sealed import copy_records

    onnx, _ = require_onnx()
    in_shape = tuple(bundle.manifest[C.M_IO]["input_shape"])
    batch = {0: "batch"}
    try:
        with staged_dir(out, what="export folder") as tmp:
            x0 = torch.zeros(2, *in_shape)
            module = bundle.loaded.module.eval()
            _export(module, (x0,), tmp / C.BASE_GRAPH, ["x"], ["y"], {"x": batch, "y": batch}, s.opset)
            onnx.checker.check_model(str(tmp / C.BASE_GRAPH))
            copy_records(Path(bundle.path), tmp, bundle.manifest)
            meta = stamp(_sealed_meta(bundle, tmp, s.opset, s.atol), C.EXPORT_DIGEST)
            (tmp / C.EXPORT_META).write_text(dump_json(meta))
            table = verify_graphs(bundle, tmp, key=key, inputs=inputs, seed=s.seed, atol=s.atol)
            if not all(r["ok"] for r in table):
                raise _VerificationFailed
    except _VerificationFailed:
        return ExportResult(out, s.opset, s.atol, [], table, False, meta)
    files = [C.BASE_GRAPH, C.EXPORT_META, *(r["file"] for r in bundle.manifest[C.M_RECORDS])]
    return ExportResult(out, s.opset, s.atol, files, table, True, meta)


def _sealed_meta(bundle: Bundle, folder: Path, opset: int, atol: float) -> dict:
    from .sealed import public_part

    m = bundle.manifest
    params = _gemm_params(folder / C.BASE_GRAPH, bundle.layer_names)
    return {
        "format": C.EXPORT_FORMAT,
        "mode": C.MODE_SEALED,
        "exporter": f"torch {torch.__version__} (TorchScript-based, dynamo=False)",
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


def _verify_sealed(
    bundle: Bundle, folder: Path, key: np.ndarray | None, x: np.ndarray, rng: np.random.Generator, atol: float
) -> list[dict]:
    """onnxruntime vs torch for a sealed export: no key, a random key and ``key`` (the user's)."""
    from .onnx_runtime import SealedOnnxPolicy
    from .policy import KeyedPolicy

    keys = [("null", None), ("random", rng.integers(0, 2, bundle.key_bits).astype(np.uint8))]
    if key is not None:
        keys.append(("user", np.asarray(key, np.uint8)))
    rows = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the random key opens nothing, by design
        for key_name, bits in keys:
            ref = KeyedPolicy(bundle, bits)(x).astype(np.float64)
            got = SealedOnnxPolicy(folder, bits, threads=1)(x)
            a, r = _diff(np.asarray(got), ref)
            rows.append(
                {"graph": C.BASE_GRAPH, "key": key_name, "max_abs": a, "max_rel": r, "ok": bool(a <= atol)}
            )
    return rows


def _export_all(km, folder: Path, in_shape: tuple, names: list[str], opset: int) -> None:
    # Placeholder trace inputs only: nothing derived from a real key may reach the exporter.
    x0 = torch.zeros(2, *in_shape)
    code0 = torch.ones(1, km.encoder.code_bits)
    ones = tuple(torch.ones(1, f) for f in km.encoder.features)
    batch = {0: "batch"}
    with DeltaPolicy(km.module, km.layer_names) as policy:
        _export(km.module, (x0,), folder / C.BASE_GRAPH, ["x"], ["y"], {"x": batch, "y": batch}, opset)
        _export(
            policy,
            (x0, *ones),
            folder / C.POLICY_GRAPH,
            ["x", *names],
            ["y"],
            {"x": batch, "y": batch},
            opset,
        )
        _export(
            _KeyedGraph(km.encoder, policy),
            (x0, code0),
            folder / C.KEYED_GRAPH,
            ["x", "code"],
            ["y"],
            {"x": batch, "y": batch},
            opset,
        )
    _export(
        _EncoderGraph(km.encoder),
        (code0,),
        folder / C.ENCODER_GRAPH,
        ["code"],
        names,
        {n: {0: "keys"} for n in ["code", *names]},
        opset,
    )


@contextlib.contextmanager
def _stdout_to_stderr():
    """Point file descriptor 1 (and sys.stdout) at stderr: the exporter prints from C++ too."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        os.dup2(2, 1)
        with contextlib.redirect_stdout(sys.stderr):
            yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def _export(module, args, path: Path, inputs, outputs, axes, opset: int) -> None:
    try:
        # On failure the exporter prints its IR graph to stdout, where our results go: divert it.
        with warnings.catch_warnings(), torch.no_grad(), _stdout_to_stderr():
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


# torch >= 2.5 takes `dynamo`; older versions only have the TorchScript exporter.
_LEGACY_EXPORTER = {"dynamo": False} if "dynamo" in inspect.signature(torch.onnx.export).parameters else {}


def _verify_inputs(bundle: Bundle, inputs: np.ndarray | None, rng: np.random.Generator) -> np.ndarray:
    """The inputs verification runs on: the given ones (up to 64), or random ones of the bundle's shape."""
    if inputs is not None:
        return np.ascontiguousarray(inputs[:64], dtype=np.float32)
    in_shape = tuple(bundle.manifest[C.M_IO]["input_shape"])
    return rng.standard_normal((VERIFY_BATCH, *in_shape)).astype(np.float32)


def _diff(got: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    """Max abs difference, and the same relative to the largest reference magnitude."""
    d = float(np.max(np.abs(got.astype(np.float64) - ref))) if ref.size else 0.0
    scale = float(np.max(np.abs(ref))) if ref.size else 0.0
    return d, d / max(scale, 1e-12)


@torch.no_grad()
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
    x = _verify_inputs(bundle, inputs, rng)
    if bundle.is_sealed:
        return _verify_sealed(bundle, folder, key, x, rng, atol)
    km = bundle.keyed.eval()
    xt = torch.from_numpy(x)
    names = delta_names(len(km.layer_names))
    sess = {g: session(folder / g, threads=1) for g in C.GRAPHS}
    rows: list[dict] = []

    def add(graph: str, key_name: str, got, ref) -> None:
        a, r = _diff(np.asarray(got), ref.numpy().astype(np.float64))
        rows.append({"graph": graph, "key": key_name, "max_abs": a, "max_rel": r, "ok": bool(a <= atol)})

    base = km.module(xt)
    add(C.BASE_GRAPH, "null", sess[C.BASE_GRAPH].run(["y"], {"x": x})[0], base)
    ones = {n: np.ones((1, f), np.float32) for n, f in zip(names, km.encoder.features)}
    add(C.POLICY_GRAPH, "null", sess[C.POLICY_GRAPH].run(["y"], {"x": x, **ones})[0], base)

    keys = [("random", rng.integers(0, 2, bundle.key_bits).astype(np.uint8))]
    if key is not None:
        keys.append(("user", np.asarray(key, np.uint8)))
    for key_name, bits in keys:
        code = key_codes(bits, bundle.key_encoding)
        deltas = km.layer_deltas(code)
        ref = km.run_keys(xt, deltas)[0]  # the training-time path, not the export wrapper
        code_np = code.numpy()
        got_d = sess[C.ENCODER_GRAPH].run(names, {"code": code_np})
        add(
            C.ENCODER_GRAPH,
            key_name,
            np.concatenate([g.ravel() for g in got_d]),
            torch.cat([d.ravel() for d in deltas]),
        )
        feed = dict(zip(names, got_d))
        add(C.POLICY_GRAPH, key_name, sess[C.POLICY_GRAPH].run(["y"], {"x": x, **feed})[0], ref)
        add(C.KEYED_GRAPH, key_name, sess[C.KEYED_GRAPH].run(["y"], {"x": x, "code": code_np})[0], ref)
    return rows


def _export_meta(bundle: Bundle, folder: Path, names: list[str], opset: int, atol: float) -> dict:
    """export.json: enough to feed the graphs without prop, and to tie them to their bundle."""
    m = bundle.manifest
    weights = _gemm_weights(folder / C.BASE_GRAPH, [layer["name"] for layer in m[C.M_KEYED_LAYERS]])
    return {
        "format": C.EXPORT_FORMAT,
        "exporter": f"torch {torch.__version__} (TorchScript-based, dynamo=False)",
        "opset": opset,
        "verified_atol": atol,
        "bundle_files": dict(m[C.M_FILES]),  # sha256 of the bundle's weights: detects a stale export
        "input_shape": list(m[C.M_IO]["input_shape"]),
        "key": {"bits": int(m[C.M_KEY]["bits"]), "encoding": m[C.M_KEY]["encoding"]},
        "code": "float32 (1, bits) of ±1; see README 'Deploy' for computing it from the key",
        "deltas": [
            {
                "input": n,
                "layer": layer["name"],
                "features": int(layer["features"]),
                "base_weight": weights.get(layer["name"]),
            }
            for n, layer in zip(names, m[C.M_KEYED_LAYERS])
        ],
        "graphs": {g: sha256_file(folder / g) for g in C.GRAPHS},
    }


def _gemm_params(path: Path, layers: list[str]) -> dict[str, tuple[str, str | None]]:
    """Keyed layer -> (weight, bias) initializers in ``path`` where the layer is a Gemm with transB=1
    whose initializers nothing else uses: then the layer's weights can be replaced in memory."""
    onnx, _ = require_onnx()
    graph = onnx.load(str(path)).graph
    inits = {i.name for i in graph.initializer}
    uses: dict[str, int] = {}
    for node in graph.node:
        for name in node.input:
            uses[name] = uses.get(name, 0) + 1
    found: dict[str, tuple[str, str | None]] = {}
    for node in graph.node:
        attrs = {a.name: a.i for a in node.attribute}
        if node.op_type != "Gemm" or attrs.get("transB") != 1 or len(node.input) < 2:
            continue
        w = node.input[1]
        bias = node.input[2] if len(node.input) > 2 and node.input[2] in inits else None
        if w in inits and uses.get(w) == 1 and w.endswith(".weight") and w[: -len(".weight")] in layers:
            found[w[: -len(".weight")]] = (w, bias if bias and uses.get(bias) == 1 else None)
    return found


def _gemm_weights(path: Path, layers: list[str]) -> dict[str, str]:
    """Keyed layer -> its weight initializer in base.onnx, where that is a Gemm's B with transB=1.

    Only then is W diag(delta) a column scaling of that initializer (OnnxPolicy's fold path).
    """
    onnx, _ = require_onnx()
    graph = onnx.load(str(path)).graph
    inits = {i.name for i in graph.initializer}
    uses: dict[str, int] = {}
    as_gemm_b = set()
    for node in graph.node:
        for name in node.input:
            uses[name] = uses.get(name, 0) + 1
        attrs = {a.name: a.i for a in node.attribute}
        if node.op_type == "Gemm" and attrs.get("transB") == 1 and len(node.input) > 1:
            as_gemm_b.add(node.input[1])
    # A weight used anywhere else (shared/tied) cannot be scaled for this layer alone.
    ok = {w for w in as_gemm_b if w in inits and uses.get(w) == 1}
    return {n: f"{n}.weight" for n in layers if f"{n}.weight" in ok}
