"""ONNX export of a bundle, checked by onnxruntime, and running the exported graphs.

Four graphs are written (names in ``GRAPHS``):

- ``base.onnx``     x -> y: what the base weights compute with no key (a drop-in for the original).
- ``keyed.onnx``    (x, code) -> y with the key encoder inside the graph.
- ``encoder.onnx``  code -> delta_1..delta_L, one scale vector per keyed layer.
- ``policy.onnx``   (x, delta_1..delta_L) -> y: a control loop computes delta once per session with
  ``encoder.onnx``, then each step costs a base step plus one multiply per keyed layer.

The key input is the encoder's ±1 *code*, not the key bits: the default "hashed" encoding is
SHAKE-256 of the bits, which ONNX cannot express. The runtime computes the code with
:func:`prop_cli.keyed.key_codes` (or the three-line hashlib recipe in the README).

No graph holds key material or weights folded with a key: the key enters only as a graph input at
run time, and the graphs are traced with placeholder inputs (zeros, a code of ones, deltas of ones).

Exporter: torch's TorchScript-based exporter (``dynamo=False``). It needs no extra package
(the torch.export-based one needs onnxscript), works offline and supports ``dynamic_axes``.
"""

from __future__ import annotations

import contextlib
import inspect
import json
import os
import re
import shutil
import sys
import tempfile
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn

from . import constants as C
from .bundle import Bundle, _replace_dir, check_output, dump_json, sha256_file
from .errors import PropError
from .keyed import key_codes

BASE_GRAPH = "base.onnx"
KEYED_GRAPH = "keyed.onnx"
ENCODER_GRAPH = "encoder.onnx"
POLICY_GRAPH = "policy.onnx"
GRAPHS = (BASE_GRAPH, KEYED_GRAPH, ENCODER_GRAPH, POLICY_GRAPH)
EXPORT_META = "export.json"  # what was exported, for which bundle, and how to feed it
EXPORT_DIR = "onnx"  # default place: <bundle>/onnx
EXPORT_FORMAT = 1

# Opset 18 runs on every onnxruntime since 1.14; the TorchScript exporter goes up to 20.
DEFAULT_OPSET = 18
MIN_OPSET, MAX_OPSET = 13, 20
DEFAULT_ATOL = 1e-5
VERIFY_BATCH = 16
ONNX_EXTRA = "pip install 'prop-cli[onnx]'"


def require_onnx():
    """(onnx, onnxruntime), or a PropError naming the extra to install."""
    try:
        import onnx
        import onnxruntime
    except ImportError as e:
        raise PropError(f"ONNX support needs the 'onnx' extra ({e.name} is not installed)", ONNX_EXTRA) from e
    return onnx, onnxruntime


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
    *,
    opset: int = DEFAULT_OPSET,
    atol: float = DEFAULT_ATOL,
    key: np.ndarray | None = None,
    inputs: np.ndarray | None = None,
    force: bool = False,
    seed: int = 0,
) -> ExportResult:
    """Write the four graphs to ``out`` (default ``<bundle>/onnx``) and verify them with onnxruntime.

    Verification compares onnxruntime with torch for the null key, a random key and ``key`` (the
    user's, if given) on ``inputs`` (or random inputs of the bundle's input shape). Files are
    written to a temporary folder and renamed into place only if every difference is <= ``atol``;
    otherwise nothing is left behind and ``ok`` is False.
    """
    onnx, _ = require_onnx()
    if not MIN_OPSET <= opset <= MAX_OPSET:
        raise PropError(
            f"--opset {opset} is not supported", f"use {MIN_OPSET}..{MAX_OPSET} (default {DEFAULT_OPSET})"
        )
    if not atol > 0:
        raise PropError(f"--atol {atol} must be positive", f"e.g. --atol {DEFAULT_ATOL}")
    if key is not None and len(key) != bundle.key_bits:
        raise PropError(
            f"the key has {len(key)} bits but the bundle expects {bundle.key_bits}",
            "use the key the bundle was personalized with",
        )
    out = Path(out) if out is not None else Path(bundle.path) / EXPORT_DIR
    check_output(out, force, what="export folder")
    km = bundle.keyed.eval()
    names = delta_names(len(km.layer_names))
    in_shape = tuple(bundle.manifest[C.M_IO]["input_shape"])
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.resolve().parent))
    try:
        _export_all(km, tmp, in_shape, names, opset)
        for g in GRAPHS:
            onnx.checker.check_model(str(tmp / g))
        table = verify_graphs(bundle, tmp, key=key, inputs=inputs, seed=seed, atol=atol)
        ok = all(r["ok"] for r in table)
        meta = _export_meta(bundle, tmp, names, opset, atol)
        if not ok:
            shutil.rmtree(tmp, ignore_errors=True)
            return ExportResult(out, opset, atol, [], table, False, meta)
        (tmp / EXPORT_META).write_text(dump_json(meta))
        _replace_dir(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return ExportResult(out, opset, atol, [*GRAPHS, EXPORT_META], table, True, meta)


def _export_all(km, folder: Path, in_shape: tuple, names: list[str], opset: int) -> None:
    # Placeholder trace inputs only: nothing derived from a real key may reach the exporter.
    x0 = torch.zeros(2, *in_shape)
    code0 = torch.ones(1, km.encoder.code_bits)
    ones = tuple(torch.ones(1, f) for f in km.encoder.features)
    batch = {0: "batch"}
    with DeltaPolicy(km.module, km.layer_names) as policy:
        _export(km.module, (x0,), folder / BASE_GRAPH, ["x"], ["y"], {"x": batch, "y": batch}, opset)
        _export(
            policy,
            (x0, *ones),
            folder / POLICY_GRAPH,
            ["x", *names],
            ["y"],
            {"x": batch, "y": batch},
            opset,
        )
        _export(
            _KeyedGraph(km.encoder, policy),
            (x0, code0),
            folder / KEYED_GRAPH,
            ["x", "code"],
            ["y"],
            {"x": batch, "y": batch},
            opset,
        )
    _export(
        _EncoderGraph(km.encoder),
        (code0,),
        folder / ENCODER_GRAPH,
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
            f"try another --opset ({MIN_OPSET}..{MAX_OPSET}), or replace that operation in the model",
        ) from e


# torch >= 2.5 takes `dynamo`; older versions only have the TorchScript exporter.
_LEGACY_EXPORTER = {"dynamo": False} if "dynamo" in inspect.signature(torch.onnx.export).parameters else {}


def _session(path: Path, threads: int = 0):
    _, ort = require_onnx()
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.log_severity_level = 3
    return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])


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
    atol: float = DEFAULT_ATOL,
) -> list[dict]:
    """onnxruntime vs torch for every graph in ``folder`` and every key: a list of table rows."""
    km = bundle.keyed.eval()
    rng = np.random.default_rng(seed)
    in_shape = tuple(bundle.manifest[C.M_IO]["input_shape"])
    if inputs is None:
        x = rng.standard_normal((VERIFY_BATCH, *in_shape)).astype(np.float32)
    else:
        x = np.ascontiguousarray(inputs[:64], dtype=np.float32)
    xt = torch.from_numpy(x)
    names = delta_names(len(km.layer_names))
    sess = {g: _session(folder / g, threads=1) for g in GRAPHS}
    rows: list[dict] = []

    def add(graph: str, key_name: str, got, ref) -> None:
        a, r = _diff(np.asarray(got), ref.numpy().astype(np.float64))
        rows.append({"graph": graph, "key": key_name, "max_abs": a, "max_rel": r, "ok": bool(a <= atol)})

    base = km.module(xt)
    add(BASE_GRAPH, "null", sess[BASE_GRAPH].run(["y"], {"x": x})[0], base)
    ones = {n: np.ones((1, f), np.float32) for n, f in zip(names, km.encoder.features)}
    add(POLICY_GRAPH, "null", sess[POLICY_GRAPH].run(["y"], {"x": x, **ones})[0], base)

    keys = [("random", rng.integers(0, 2, bundle.key_bits).astype(np.uint8))]
    if key is not None:
        keys.append(("user", np.asarray(key, np.uint8)))
    for key_name, bits in keys:
        code = key_codes(bits, bundle.key_encoding)
        deltas = km.layer_deltas(code)
        ref = km.run_keys(xt, deltas)[0]  # the training-time path, not the export wrapper
        code_np = code.numpy()
        got_d = sess[ENCODER_GRAPH].run(names, {"code": code_np})
        add(
            ENCODER_GRAPH,
            key_name,
            np.concatenate([g.ravel() for g in got_d]),
            torch.cat([d.ravel() for d in deltas]),
        )
        feed = dict(zip(names, got_d))
        add(POLICY_GRAPH, key_name, sess[POLICY_GRAPH].run(["y"], {"x": x, **feed})[0], ref)
        add(KEYED_GRAPH, key_name, sess[KEYED_GRAPH].run(["y"], {"x": x, "code": code_np})[0], ref)
    return rows


def _export_meta(bundle: Bundle, folder: Path, names: list[str], opset: int, atol: float) -> dict:
    """export.json: enough to feed the graphs without prop, and to tie them to their bundle."""
    m = bundle.manifest
    weights = _gemm_weights(folder / BASE_GRAPH, [layer["name"] for layer in m[C.M_KEYED_LAYERS]])
    return {
        "format": EXPORT_FORMAT,
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
        "graphs": {g: sha256_file(folder / g) for g in GRAPHS},
    }


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


def read_export(folder: Path, bundle_manifest: dict | None = None) -> dict:
    """Read and check ``export.json`` (graph hashes; with a manifest, that it matches the bundle)."""
    folder = Path(folder)
    mpath = folder / EXPORT_META
    if not mpath.is_file():
        raise PropError(
            f"{folder} holds no ONNX export ({EXPORT_META} missing)", "run prop export BUNDLE --onnx"
        )
    try:
        meta = json.loads(mpath.read_text())
        graphs = meta["graphs"]
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError) as e:
        raise PropError(f"{mpath} is not a valid export description", "run prop export --onnx --force") from e
    for g, digest in graphs.items():
        if not (folder / g).is_file() or sha256_file(folder / g) != digest:
            raise PropError(f"{folder / g} is missing or modified", "run prop export --onnx --force")
    if bundle_manifest is not None and meta.get("bundle_files") != bundle_manifest.get(C.M_FILES):
        raise PropError(
            f"the ONNX export in {folder} was made from another bundle (or an older version of it)",
            "run prop export BUNDLE --onnx --force",
        )
    return meta


class OnnxPolicy:
    """Run an export with onnxruntime, one control step per call: ``policy(x) -> y``.

    With a key, delta is computed once here (encoder.onnx) and bound to policy.onnx, so a step
    feeds only x; without a key each call runs base.onnx. Calls go through an IOBinding, the
    cheapest per-call path at batch 1. ``fold=True`` instead runs base.onnx with the keyed layers'
    weights replaced, in this process's memory only, by W diag(delta) (onnxruntime initializer
    overrides): a step then costs exactly a base step. Nothing folded is ever written. ``threads``
    = 0 lets onnxruntime choose. Not thread-safe (one binding per instance).
    """

    def __init__(
        self, folder: Path, key_code: np.ndarray | None = None, threads: int = 0, fold: bool = False
    ) -> None:
        _, ort = require_onnx()
        folder = Path(folder)
        self.meta = read_export(folder)
        self.names = [d["input"] for d in self.meta["deltas"]]
        self._keep: list = []  # OrtValues the session reads from must outlive it
        bound: dict = {}
        if key_code is None:
            self.session = _session(folder / BASE_GRAPH, threads)
        else:
            code = np.asarray(key_code, np.float32).reshape(1, -1)
            deltas = _session(folder / ENCODER_GRAPH, threads).run(self.names, {"code": code})
            if fold:
                self.session = self._folded(folder, deltas, threads, ort)
            else:
                self.session = _session(folder / POLICY_GRAPH, threads)
                bound = {n: ort.OrtValue.ortvalue_from_numpy(d) for n, d in zip(self.names, deltas)}
                self._keep += bound.values()
        self._binding = self.session.io_binding()
        for n, v in bound.items():
            self._binding.bind_ortvalue_input(n, v)
        self._binding.bind_output("y")

    def _folded(self, folder: Path, deltas: list[np.ndarray], threads: int, ort):
        onnx, _ = require_onnx()
        from onnx import numpy_helper

        weights = [d.get("base_weight") for d in self.meta["deltas"]]
        if not all(weights):
            raise PropError(
                f"{folder / BASE_GRAPH} does not expose the keyed layers' weights by name",
                "run without fold (the split form, policy.onnx)",
            )
        inits = {i.name: i for i in onnx.load(str(folder / BASE_GRAPH)).graph.initializer}
        so = ort.SessionOptions()
        so.intra_op_num_threads, so.inter_op_num_threads, so.log_severity_level = threads, 1, 3
        for name, d in zip(weights, deltas):
            w = numpy_helper.to_array(inits[name]) * d.reshape(1, -1)  # Gemm B (out, in), transB=1
            v = ort.OrtValue.ortvalue_from_numpy(np.ascontiguousarray(w, np.float32))
            self._keep.append(v)
            so.add_initializer(name, v)
        return ort.InferenceSession(str(folder / BASE_GRAPH), so, providers=["CPUExecutionProvider"])

    def __call__(self, x: np.ndarray) -> np.ndarray:
        self._binding.bind_cpu_input("x", np.ascontiguousarray(x, np.float32))
        self.session.run_with_iobinding(self._binding)
        return self._binding.copy_outputs_to_cpu()[0]


def run_onnx(bundle: Bundle, x: np.ndarray, key: np.ndarray | None, folder: Path | None = None) -> np.ndarray:
    """`prop run --onnx`: the bundle's outputs computed by its exported graphs (split form)."""
    require_onnx()
    folder = Path(folder) if folder is not None else Path(bundle.path) / EXPORT_DIR
    if not folder.is_dir():
        raise PropError(
            f"no ONNX export at {folder}", "run prop export BUNDLE --onnx first, or pass --onnx-dir"
        )
    read_export(folder, bundle.manifest)
    code = None
    if key is not None:
        if len(key) != bundle.key_bits:
            raise PropError(
                f"the key has {len(key)} bits but the bundle expects {bundle.key_bits}",
                "use the key the bundle was personalized with",
            )
        code = key_codes(key, bundle.key_encoding).numpy()
    threads = int(os.environ.get("OMP_NUM_THREADS", "0") or 0)
    return OnnxPolicy(folder, code, threads=threads)(x)
