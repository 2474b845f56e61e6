"""ONNX export of an unsealed bundle, and running it.

Four graphs are written (names in ``constants.GRAPHS``):

- ``base.onnx``     x -> y: what the base weights compute with no key (a drop-in for the original).
- ``keyed_model.onnx``    (x, code) -> y with the key encoder inside the graph.
- ``encoder.onnx``  code -> delta_1..delta_L, one scale vector per keyed layer.
- ``policy.onnx``   (x, delta_1..delta_L) -> y: a control loop computes delta once per session with
  ``encoder.onnx``, then each step costs a base step plus one multiply per keyed layer.

The key input is the encoder's ±1 *code*, not the key bits: the default "hashed" encoding is
SHAKE-256 of the bits, which ONNX cannot express. The runtime computes the code with
:func:`prop_cli.core.keyed_model.key_codes` (or the three-line hashlib recipe in docs/deploy.md).

No graph holds key material or weights folded with a key: the key enters only as a graph input at
run time, and the graphs are traced with placeholder inputs (zeros, a code of ones, deltas of ones).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn

from prop_cli import constants as C
from prop_cli.bundle import Bundle
from prop_cli.bundle.enrol import BUNDLE_ID, ID, VERSION, open_enrolment
from prop_cli.bundle.manifest import Doc, quoted, stamp
from prop_cli.config import ExportSettings
from prop_cli.core.keyed_model import KeyedModel, key_codes
from prop_cli.core.layers import is_conv, scale_inputs
from prop_cli.errors import PropError, brief
from prop_cli.files import dump_json, sha256_file, staged_dir

from .common import (
    EXPORTER,
    REEXPORT,
    ExportResult,
    VerificationFailed,
    add_weight,
    bind,
    bound,
    check_opened,
    diff_row,
    export_graph,
    gemm_params,
    identity,
    key_bits,
    load_graph,
    not_bound,
    open_session,
    read_export,
    require_mode,
    require_onnx,
    session,
    session_options,
)


def delta_names(n_layers: int) -> list[str]:
    return [f"delta_{i + 1}" for i in range(n_layers)]


class DeltaInputView(nn.Module):
    """Export-only view of the keyed model: ``(x, delta_1..delta_L) -> y``.

    Pre-hooks on the keyed layers multiply the layer input by a delta given as a graph input,
    shape (1, d_i), broadcast over the batch (and any middle axes; a convolution's channel axis,
    viewed as (1, d_i, 1, ...)). This is Eq. 5's W diag(delta) z without KeyedModel's
    row-gathering state, which does not trace to ONNX.
    Use as a context manager: the hooks are removed from the bundle's module on exit.
    """

    def __init__(self, module: nn.Module, layer_names: list[str]) -> None:
        super().__init__()
        self.module = module
        self._deltas: tuple[torch.Tensor, ...] | None = None
        mods = dict(module.named_modules())
        self._handles = [
            mods[name].register_forward_pre_hook(self._hook(i, is_conv(mods[name])))
            for i, name in enumerate(layer_names)
        ]

    def _hook(self, i: int, conv: bool):
        def pre(mod: nn.Module, args: tuple):
            if self._deltas is None:
                return None
            d, z = self._deltas[i], args[0]
            if conv:
                d = d.view(d.shape[0], d.shape[1], *([1] * (z.dim() - 2)))
            return (z * d, *args[1:])

        return pre

    def forward(self, x: torch.Tensor, *deltas: torch.Tensor) -> torch.Tensor:
        self._deltas = deltas
        try:
            return self.module(x)
        finally:
            self._deltas = None

    def __enter__(self) -> DeltaInputView:
        return self

    def __exit__(self, *exc) -> None:
        for h in self._handles:
            h.remove()


class _KeyedGraph(nn.Module):
    """(x, code) -> y: the encoder feeding the delta policy."""

    def __init__(self, encoder: nn.Module, policy: DeltaInputView) -> None:
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


def _export_all(km: KeyedModel, folder: Path, in_shape: tuple, names: list[str], opset: int) -> None:
    # Placeholder trace inputs only: nothing derived from a real key may reach the exporter.
    x0 = torch.zeros(2, *in_shape)
    code0 = torch.ones(1, km.encoder.code_bits)
    ones = tuple(torch.ones(1, f) for f in km.encoder.features)
    batch = {"x": {0: "batch"}, "y": {0: "batch"}}
    with DeltaInputView(km.module, km.layer_names) as policy:
        export_graph(km.module, (x0,), folder / C.BASE_GRAPH, ["x"], ["y"], batch, opset)
        export_graph(policy, (x0, *ones), folder / C.POLICY_GRAPH, ["x", *names], ["y"], batch, opset)
        graph = _KeyedGraph(km.encoder, policy)
        export_graph(graph, (x0, code0), folder / C.KEYED_GRAPH, ["x", "code"], ["y"], batch, opset)
    axes = {n: {0: "keys"} for n in ["code", *names]}
    export_graph(_EncoderGraph(km.encoder), (code0,), folder / C.ENCODER_GRAPH, ["code"], names, axes, opset)


def export(bundle: Bundle, out: Path, s: ExportSettings, key: np.ndarray | None, verify) -> ExportResult:
    """Write the four graphs and ``export.json`` to ``out``, if ``verify(folder)`` (onnxruntime against
    torch) passes; otherwise nothing is left behind and the result is not ok."""
    onnx, _ = require_onnx()
    km = bundle.keyed.eval()
    names = delta_names(len(km.layer_names))
    in_shape = tuple(bundle.manifest[C.M_IO]["input_shape"])
    try:
        with staged_dir(out, what="export folder") as tmp:
            _export_all(km, tmp, in_shape, names, s.opset)
            for g in C.GRAPHS:
                onnx.checker.check_model(str(tmp / g))
            table = verify(tmp)
            meta = _export_meta(bundle, tmp, names, s.opset, s.atol)
            if not all(r["ok"] for r in table):
                raise VerificationFailed  # staged_dir removes the folder: nothing is left behind
            meta = stamp(
                {**meta, C.M_ENROLMENTS: bind(meta, bundle, key, _user(bundle, key))}, C.EXPORT_DIGEST
            )
            (tmp / C.EXPORT_META).write_text(dump_json(meta))
    except VerificationFailed:
        return ExportResult(out, s.opset, s.atol, [], table, False, meta)
    return ExportResult(out, s.opset, s.atol, [*C.GRAPHS, C.EXPORT_META], table, True, meta)


def _user(bundle: Bundle, key: np.ndarray | None) -> dict | None:
    """The enrolment ``key`` opens in the bundle: its id and the version it was written in (format 5)."""
    if key is None:
        return None
    entry = open_enrolment(bundle.manifest.get(C.M_ENROLMENTS, []), key) or {}
    return {"id": entry.get(ID), "version": int(entry.get(VERSION, 0))}


def check_meta(meta: dict, doc: Doc) -> None:
    """What the rules of an unsealed export's fields cannot say: ``deltas`` are the encoder's outputs in
    order (delta_1, delta_2, ...), one per keyed layer."""
    inputs = [d["input"] for d in meta["deltas"]]
    if inputs != delta_names(len(inputs)):
        raise doc.bad("deltas", "must be delta_1, delta_2, ... in order (the encoder's outputs)")
    layers = [d["layer"] for d in meta["deltas"]]
    if len(set(layers)) != len(layers):
        raise doc.bad("deltas", "names a layer twice")


@torch.no_grad()
def verify(
    bundle: Bundle, folder: Path, key: np.ndarray | None, x: np.ndarray, rng: np.random.Generator, atol: float
) -> list[dict]:
    """onnxruntime vs torch for every graph: no key, a random key and ``key`` (the user's)."""
    km = bundle.keyed.eval()
    xt = torch.from_numpy(x)
    names = delta_names(len(km.layer_names))
    sess = {g: session(folder / g, threads=1) for g in C.GRAPHS}
    rows: list[dict] = []

    def add(graph: str, key_name: str, got, ref: torch.Tensor) -> None:
        rows.append(diff_row(graph, key_name, got, ref.numpy(), atol))

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
    params = gemm_params(folder / C.BASE_GRAPH, [layer["name"] for layer in m[C.M_KEYED_LAYERS]])
    return {
        **identity(m),
        "format": C.EXPORT_FORMAT,
        "exporter": EXPORTER,
        "opset": opset,
        "verified_atol": atol,
        "bundle_files": dict(m[C.M_FILES]),  # sha256 of the bundle's weights: detects a stale export
        "input_shape": list(m[C.M_IO]["input_shape"]),
        "key": {"bits": int(m[C.M_KEY]["bits"]), "encoding": m[C.M_KEY]["encoding"]},
        "code": "float32 (1, bits) of ±1; see docs/deploy.md for computing it from the key",
        "deltas": [
            {
                "input": n,
                "layer": layer["name"],
                "features": int(layer["features"]),
                "base_weight": params[layer["name"]][0] if layer["name"] in params else None,
            }
            for n, layer in zip(names, m[C.M_KEYED_LAYERS])
        ],
        "graphs": {g: sha256_file(folder / g) for g in C.GRAPHS},
    }


class OnnxRunner:
    """Run an export with onnxruntime, one control step per call: ``policy(x) -> y``.

    ``key``: the key bits. It runs only if export.json binds it to these graphs (``prop export --onnx
    --key-file``): a key the export does not bind is refused (``allow_unenrolled``: base.onnx runs, with a
    warning); graphs changed since it was bound are refused. ``code``: the encoder's input given directly,
    unchecked (the method itself, for benchmarks and audits). With a key, delta is computed once here
    (encoder.onnx). Folded (the default where the export names the keyed layers' weights): base.onnx runs with
    those weights replaced, in this process's memory only, by W diag(delta) (onnxruntime initializer
    overrides), so a step costs a base step (the split form measured 1.1-1.2x base.onnx: an extra Mul per
    keyed layer; benchmarks/table.py). Nothing folded is ever written. ``fold=False``: the split form, delta
    bound to policy.onnx. Without a key each call runs base.onnx. Calls go through an IOBinding, the cheapest
    per-call path at batch 1. ``threads`` = 0 lets onnxruntime choose. Not thread-safe (one binding per
    instance).
    """

    def __init__(
        self, folder: Path, key: np.ndarray | None = None, threads: int = 0, fold: bool | None = None,
        *, code: np.ndarray | None = None, allow_unenrolled: bool = False, allow_rollback: bool = False,
    ) -> None:  # fmt: skip
        _, ort = require_onnx()
        folder = Path(folder)
        self.meta = read_export(folder)
        check_meta(self.meta, require_mode(self.meta, folder, C.MODE_UNSEALED))
        self.names = [d["input"] for d in self.meta["deltas"]]
        key_code = code
        if key is not None:
            bits = key_bits(key, self.meta["key"]["bits"])
            binding = bound(self.meta, bits, folder)
            if binding is not None:
                # The enrolment the key was bound with: checked as torch checks the bundle's (rollback).
                user, versioned = binding.get("user") or {}, BUNDLE_ID in binding.get("bundle", {})
                uid, version = user.get("id"), user.get("version", 0)
                check_opened(self.meta, folder, uid, version, versioned, allow_rollback)
                key_code = key_codes(bits, self.meta["key"]["encoding"]).numpy()
            else:
                not_bound(folder, allow_unenrolled)
        self._keep: list = []  # OrtValues the session reads from must outlive it
        feeds: dict = {}
        if key_code is None:
            self.session = session(folder / C.BASE_GRAPH, threads)
        else:
            code = np.asarray(key_code, np.float32).reshape(1, -1)
            deltas = self._deltas(folder, code, threads)
            if fold is None:
                fold = all(d.get("base_weight") for d in self.meta["deltas"])
            if fold:
                self.session = self._folded(folder, deltas, threads, ort)
            else:
                self.session = session(folder / C.POLICY_GRAPH, threads)
                feeds = {n: ort.OrtValue.ortvalue_from_numpy(d) for n, d in zip(self.names, deltas)}
                self._keep += feeds.values()
        self._binding = self.session.io_binding()
        try:
            for n, v in feeds.items():
                self._binding.bind_ortvalue_input(n, v)
        except Exception as e:  # noqa: BLE001 - onnxruntime's own types: an input policy.onnx lacks
            what = f"{folder / C.POLICY_GRAPH} does not take the inputs export.json names ({brief(e)})"
            raise PropError(what, REEXPORT) from None
        self._binding.bind_output("y")
        self._rows: int | None = None  # the batch size the output binding was last run with

    def _deltas(self, folder: Path, code: np.ndarray, threads: int) -> list[np.ndarray]:
        """delta per keyed layer: encoder.onnx on ``code``, each checked against export.json's width."""
        try:
            deltas = session(folder / C.ENCODER_GRAPH, threads).run(self.names, {"code": code})
        except PropError:
            raise
        except Exception as e:  # noqa: BLE001 - onnxruntime's own types: outputs or code of other sizes
            what = f"{folder / C.ENCODER_GRAPH} does not run as export.json describes it ({brief(e)})"
            raise PropError(what, REEXPORT) from None
        for i, (d, meta) in enumerate(zip(deltas, self.meta["deltas"])):
            if d.shape != (1, meta["features"]):
                raise PropError(
                    f"{folder / C.EXPORT_META} field 'deltas[{i}].features' is {meta['features']} but "
                    f"{C.ENCODER_GRAPH} gives {d.shape[-1]}",
                    REEXPORT,
                )
        return deltas

    def _folded(self, folder: Path, deltas: list[np.ndarray], threads: int, ort):
        from onnx import numpy_helper

        weights = [d.get("base_weight") for d in self.meta["deltas"]]
        if not all(weights):
            raise PropError(
                f"{folder / C.BASE_GRAPH} does not expose the keyed layers' weights by name",
                "run without fold (the split form, policy.onnx)",
            )
        inits = {i.name: i for i in load_graph(folder / C.BASE_GRAPH).graph.initializer}
        so = session_options(ort, threads)
        for i, (name, d) in enumerate(zip(weights, deltas)):
            w = numpy_helper.to_array(inits[name]) if name in inits else None
            if w is None or w.ndim < 2 or (w.ndim == 2 and w.shape[1] != d.size):
                raise PropError(
                    f"{folder / C.EXPORT_META} field 'deltas[{i}].base_weight' names no weight of "
                    f"{C.BASE_GRAPH} that takes {d.size} inputs ({quoted(name)})",
                    REEXPORT,
                )
            if w.ndim == 2:
                w = w * d.reshape(1, -1)  # Gemm B (out, in), transB=1
            else:  # a Conv's (out, in / groups, *kernel): scale its input channels
                t = torch.from_numpy(w.copy())
                try:
                    w = (t * scale_inputs(t, torch.from_numpy(d).flatten())).numpy()
                except (RuntimeError, ValueError) as e:
                    raise PropError(
                        f"{folder / C.EXPORT_META} field 'deltas[{i}].base_weight': {quoted(name)} does not "
                        f"take {d.size} input channels ({brief(e, 80)})",
                        REEXPORT,
                    ) from None
            add_weight(so, ort, name, w, self._keep)
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


def run(bundle: Bundle, folder: Path, x: np.ndarray, key: np.ndarray | None, threads: int) -> np.ndarray:
    return OnnxRunner(folder, key, threads=threads, allow_rollback=bundle.mode.allow_rollback)(x)
