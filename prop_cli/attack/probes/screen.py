"""Screening millions of keys on a few samples: the streamed scan behind ``ProbeContext.probe_keys_stream``.

Per chunk of keys: deltas (``ProbeContext.key_deltas``, the encoder in bf16), the model on the
screening samples, two continuous criteria per key (divergence from the reference, the attacker's;
and with targets, a screening leakage, the owner's), and a running top-``keep`` by each. Only the
kept keys are re-scored exactly (fp32, every audit sample) through ``probe_keys``.

The fast forward (:class:`ChainForward`) is for chain MLPs (``nn.Sequential`` of linear layers and
parameter-free activations, or the MLP adapter's chain): everything before the first keyed layer
runs once per sample; the first keyed layer for all keys and samples is one matmul,
``Delta (K, d) @ [W diag(z_1) | ... | W diag(z_S)] (d, S*h)``, so no (K*S, d) product is built; the
rest runs in bf16 (AMX/AVX-512 bf16 units on recent x86: several times fp32 matmul throughput) in
buffers reused across chunks. Where the CPU has no bf16 arithmetic, torch emulates it (62x fp32's time
on AVX2 kernels: a 305 s digits audit, issue 44), so the scan times both precisions on a few keys first
and screens in fp32 unless bf16 is clearly faster (``_chain``). Any other model takes
``KeyedModel.run_keys`` in fp32.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch
from torch import nn

from prop_adapters import activations
from prop_cli.core.keyed_model import KeyedModel


class Scannable(Protocol):
    """What a scan needs of its caller (``base.ProbeContext``, which calls ``scan_keys``)."""

    km: KeyedModel
    ref: object  # base.Reference: x, b, p, task
    progress: object
    counter: object

    def key_deltas(
        self, bits: np.ndarray, null: int = 0, low_precision: bool = False
    ) -> list[torch.Tensor]: ...

    def probe_keys(self, bits: np.ndarray, stage: str) -> dict[str, torch.Tensor]: ...

    def out_of_time(self, stage: str | None = None) -> bool: ...


@dataclass
class KeyScan:
    """A streamed key scan: the keys kept by screening, their exact scores, and what it cost."""

    bits: np.ndarray  # (M, key_bits) kept keys
    values: dict[str, torch.Tensor]  # exact scores of the kept keys (probe_keys)
    scanned: int
    screen_samples: int
    seconds: dict[str, float]  # per stage: calibrate, keys+deltas, model, scores, rescore
    path: str  # "bf16-chain", "fp32-chain" or "general" (run_keys, fp32)


# Relative error the bf16 forward may show against fp32 on a check batch before it is refused.
_BF16_TOLERANCE = 0.05
# bf16 screens only where a chunk (encoder and chain) takes at most this share of fp32's time. Measured on
# the project's 2-core EPYC, digits MLP, 1 thread: native bf16 (AVX512-BF16) 0.5 of fp32, emulated 2.2x
# (AVX-512 without BF16) and 62x (AVX2); the margin keeps one machine's choice, and so its kept keys, the
# same from run to run.
_BF16_SHARE = 0.8
_CALIBRATION_KEYS = 256
_RELU_LIKE = {nn.ReLU: torch.relu_, nn.Tanh: torch.tanh_}


def chain_ops(module: nn.Module) -> list[tuple[str, str, nn.Module]] | None:
    """[(kind, name, module)] with kind "linear" or "act", or None if the module is not a plain chain."""
    if hasattr(module, "layer_paths") and hasattr(module, "activation"):  # the MLP adapter's ChainMLP
        act = activations.ACTIVATIONS[module.activation]()
        ops = []
        for i, p in enumerate(module.layer_paths):
            ops.append(("linear", p, module.get_submodule(p)))
            if i < len(module.layer_paths) - 1:
                ops.append(("act", "", act))
        return ops
    if isinstance(module, nn.Sequential):
        ops = []
        for name, m in module.named_children():
            if isinstance(m, nn.Linear):
                ops.append(("linear", name, m))
            elif not list(m.parameters()) and not list(m.buffers()) and not list(m.children()):
                ops.append(("act", name, m))
            else:
                return None
        return ops
    return None


def _keyed_chain(km, x: torch.Tensor) -> tuple[list, dict[str, int], int, torch.Tensor]:
    """(the chain's ops, each keyed layer's position in ``km.layer_names``, the op index of the first
    keyed layer, ``x`` through the layers before it), or ValueError where ``km`` is not a keyed chain."""
    ops = chain_ops(km.module)
    if ops is None:
        raise ValueError("not a chain MLP")
    pos = {name: i for i, name in enumerate(km.layer_names)}
    lin_at = [i for i, (kind, name, _) in enumerate(ops) if kind == "linear" and name in pos]
    if len(lin_at) != len(pos):
        raise ValueError("keyed layers are not all in the chain")
    with torch.inference_mode():
        z = x
        for _, _, m in ops[: lin_at[0]]:
            z = m(z)
    return ops, pos, lin_at[0], z


class ChainForward:
    """Outputs (K, S, out) of a chain MLP for K keys' deltas on S fixed samples, in bf16."""

    def __init__(self, km, x: torch.Tensor, dtype: torch.dtype = torch.bfloat16) -> None:
        ops, pos, first, z = _keyed_chain(km, x)
        self.dtype = dtype
        with torch.inference_mode():
            w = ops[first][2].weight  # (h, d)
            s, d = z.shape
            h = w.shape[0]
            # a[j, s*h + i] = W[i, j] z_s[j]: Delta @ a is every key's first keyed layer on every sample.
            self.a = (w[None] * z[:, None, :]).permute(2, 0, 1).reshape(d, s * h).to(dtype).contiguous()
            bias = ops[first][2].bias
            self.b1 = (bias.repeat(s) if bias is not None else torch.zeros(s * h)).to(dtype)
            self.first = pos[ops[first][1]]
            self.rest = []  # ("act", fn) | ("linear", weight^T, bias, keyed position or None)
            for kind, name, m in ops[first + 1 :]:
                if kind == "act":
                    self.rest.append(("act", _RELU_LIKE.get(type(m)), m))
                else:
                    wt = m.weight.t().to(dtype).contiguous()
                    self.rest.append(
                        ("linear", wt, None if m.bias is None else m.bias.to(dtype), pos.get(name))
                    )
        self.samples, self.width = s, h
        self._buffers: dict[tuple, torch.Tensor] = {}

    def _buffer(self, slot: int, rows: int, cols: int) -> torch.Tensor:
        key = (slot, cols)
        buf = self._buffers.get(key)
        if buf is None or buf.shape[0] < rows:
            buf = self._buffers[key] = torch.empty(rows, cols, dtype=self.dtype)
        return buf[:rows]

    @torch.inference_mode()
    def __call__(self, deltas: list[torch.Tensor]) -> torch.Tensor:
        k, s = deltas[0].shape[0], self.samples
        d = [t.to(self.dtype) for t in deltas]
        y = torch.addmm(self.b1, d[self.first], self.a, out=self._buffer(0, k, s * self.width))
        y = y.view(k * s, self.width)
        slot = 1
        for op in self.rest:
            if op[0] == "act":
                y = op[1](y) if op[1] is not None else op[2](y)
                continue
            _, wt, bias, kp = op
            if kp is not None:
                y.view(k, s, -1).mul_(d[kp][:, None, :])
            out = self._buffer(slot, k * s, wt.shape[1])
            slot += 1
            y = torch.mm(y, wt, out=out)
            if bias is not None:
                y.add_(bias)
        return y.view(k, s, -1)


class ChainKeys:
    """Outputs (K, B, out) of a chain MLP for K keys' deltas on B samples in fp32: ``run_keys``'s own
    operations (the layers before the first keyed one once, each keyed layer's input times the key's
    delta, ``addmm`` as ``nn.Linear`` runs it), without hooks, into buffers kept from chunk to chunk and
    with the activations in place. The exact key probes' path (``ProbeContext._probe``): it leaves out
    the fresh allocations and copies that cost run_keys as much as its matmuls on a small MLP.

    The output is a buffer the next call overwrites: copy what outlives the chunk."""

    def __init__(self, km, x: torch.Tensor) -> None:
        if x.dim() != 2:
            raise ValueError("not flat inputs")
        ops, pos, first, z = _keyed_chain(km, x)
        if any(m.weight.dtype != z.dtype for kind, _, m in ops[first:] if kind == "linear"):
            raise ValueError("weights in another dtype than the inputs: run_keys's promotions apply")
        self.z, self.samples = z, len(x)
        self.ops = [(kind, m, pos.get(name) if kind == "linear" else None) for kind, name, m in ops[first:]]
        self._buffers: dict[int, torch.Tensor] = {}

    def _buffer(self, slot: int, rows: int, cols: int) -> torch.Tensor:
        buf = self._buffers.get(slot)
        if buf is None or buf.numel() < rows * cols:
            buf = self._buffers[slot] = torch.empty(rows * cols, dtype=self.z.dtype, device=self.z.device)
        return buf[: rows * cols].view(rows, cols)

    @torch.inference_mode()
    def __call__(self, deltas: list[torch.Tensor]) -> torch.Tensor:
        k, b = deltas[0].shape[0], self.samples
        y, slot = None, 0
        for kind, m, kp in self.ops:
            if kind == "act":
                fn = _RELU_LIKE.get(type(m))
                y = fn(y) if fn is not None else m(y)
                continue
            if y is None:  # the first keyed layer: every key on every sample's shared input
                y = self._buffer(slot, k * b, self.z.shape[1])
                slot += 1
                torch.mul(self.z[None], deltas[kp][:, None, :], out=y.view(k, b, -1))
            elif kp is not None:
                y.view(k, b, -1).mul_(deltas[kp][:, None, :])
            out = self._buffer(slot, k * b, m.out_features)
            slot += 1
            if m.bias is not None:
                y = torch.addmm(m.bias, y, m.weight.t(), out=out)
            else:
                y = torch.mm(y, m.weight.t(), out=out)
        return y.view(k, b, -1)


def chain_keys(km, x: torch.Tensor) -> ChainKeys | None:
    """``ChainKeys`` for ``km`` on ``x``, or None where the model is not a chain MLP (run_keys then)."""
    try:
        return ChainKeys(km, x)
    except ValueError:
        return None


def _chunk_seconds(ctx: Scannable, fast: ChainForward, bits: np.ndarray, low: bool) -> float:
    """The fastest of 3 timed runs (after a warm-up) of one calibration chunk: deltas, then the chain."""
    best = float("inf")
    with torch.inference_mode():
        for i in range(4):
            t0 = time.perf_counter()
            fast(ctx.key_deltas(bits, low_precision=low))
            if i:
                best = min(best, time.perf_counter() - t0)
    return best


def _chain(ctx: Scannable, xs: torch.Tensor) -> ChainForward | None:
    """The chain forward in the precision that screens faster on this machine (bf16 only if it agrees
    with fp32 on a check batch), or None where the model is not a chain MLP."""
    try:
        fp32 = ChainForward(ctx.km, xs, torch.float32)
        bf16 = ChainForward(ctx.km, xs)
    except ValueError:
        return None
    if not _check(bf16, ctx, xs):
        return fp32
    n = ctx.km.encoder.code_bits
    bits = np.random.default_rng(1).integers(0, 2, (_CALIBRATION_KEYS, n), dtype=np.uint8)
    fast = _chunk_seconds(ctx, bf16, bits, True) <= _BF16_SHARE * _chunk_seconds(ctx, fp32, bits, False)
    return bf16 if fast else fp32


def _check(fast: ChainForward, ctx: Scannable, xs: torch.Tensor) -> bool:
    """The bf16 chain against run_keys in fp32 on a few random keys: refuse it if it disagrees."""
    bits = np.random.default_rng(0).integers(0, 2, (4, ctx.km.encoder.code_bits), dtype=np.uint8)
    with torch.inference_mode():
        deltas = ctx.key_deltas(bits)
        want = ctx.km.run_keys(xs, deltas)
        got = fast(deltas).float().view_as(want)
    scale = want.abs().max().clamp_min(1e-6)
    return bool(((got - want).abs().max() / scale) <= _BF16_TOLERANCE)


class _Criteria:
    """Per key, from its outputs on the screening samples: divergence from the reference (what the
    attacker ranks by; as the searches' objective: mse, or KL for classification) and, with the owner's
    targets, a continuous screening leakage (ranking only; the re-score is exact). Regression: the
    metric itself; classification: the mean probability of the owner's label where it differs from
    the reference's. What depends on the samples alone is computed once."""

    def __init__(self, ref, screen: int) -> None:
        self.task = ref.task
        self.b = ref.b[:screen].float()
        self.gap = self.label = None
        if self.task == "classification":
            self.logp_b = torch.log_softmax(self.b, -1)
            self.p_b = self.logp_b.exp()
        if ref.p is None:
            return
        p = ref.p[:screen]
        if self.task == "regression":
            self.gap = (p - self.b).flatten(1)
            self.norm = (self.gap**2).sum().clamp_min(1e-12)
        else:
            differs = p != self.b.argmax(-1)
            if differs.any():
                self.rows, self.label = torch.nonzero(differs).flatten(), p[differs]

    def __call__(self, o: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        if self.task == "regression":
            move = (o - self.b).flatten(2)
            div = (move**2).mean((-2, -1))
            return div, None if self.gap is None else (move * self.gap).sum((-2, -1)) / self.norm
        logp = torch.log_softmax(o, -1)
        div = (self.p_b * (self.logp_b - logp)).sum(-1).flatten(1).mean(-1)
        if self.label is None:
            return div, None
        at = logp[:, self.rows].gather(-1, self.label[None, :, None].expand(len(o), -1, 1))
        return div, at.squeeze(-1).exp().mean(1)


def _top(values: torch.Tensor, keep: int) -> torch.Tensor:
    return values.topk(min(keep, len(values))).indices


def _deltas_ahead(ctx: Scannable, chunks: Iterable[np.ndarray], low: bool, sec: dict) -> Iterator:
    """(bits, deltas) per chunk, the next chunk's keys and deltas made on a second thread meanwhile
    (hashing holds the GIL, the model's matmuls release it: on 2 cores the two overlap)."""
    it = iter(chunks)

    def work() -> tuple | None:
        t0 = time.perf_counter()
        bits = next(it, None)
        if bits is None:
            return None
        with torch.inference_mode():  # thread-local, like autocast inside key_deltas
            deltas = ctx.key_deltas(bits, low_precision=low)
        sec["keys+deltas"] += time.perf_counter() - t0
        return bits, deltas

    with ThreadPoolExecutor(1) as pool:
        ahead = pool.submit(work)
        while (got := ahead.result()) is not None:
            ahead = pool.submit(work)
            yield got


def scan_keys(
    ctx: Scannable, chunks: Iterable[np.ndarray], total: int, stage: str, *, screen: int, keep: int
) -> KeyScan:
    xs = ctx.ref.x[:screen]
    criteria = _Criteria(ctx.ref, screen)
    t0 = time.perf_counter()
    fast = _chain(ctx, xs)
    low = fast is not None and fast.dtype == torch.bfloat16  # the encoder in bf16 where the chain is
    sec = {"calibrate": time.perf_counter() - t0, "keys+deltas": 0.0, "model": 0.0, "scores": 0.0}
    kept_bits = np.zeros((0, ctx.km.encoder.code_bits), np.uint8)
    kept_div = torch.zeros(0)
    kept_lk: torch.Tensor | None = None
    done = 0
    t_start, cpu_start = time.perf_counter(), time.process_time()
    with torch.inference_mode():
        for bits, deltas in _deltas_ahead(ctx, chunks, low, sec):
            t2 = time.perf_counter()
            o = (fast(deltas) if fast is not None else ctx.km.run_keys(xs, deltas)).float()
            t3 = time.perf_counter()
            div, lk = criteria(o)
            kept_bits = np.concatenate([kept_bits, bits])
            kept_div = torch.cat([kept_div, div])
            if lk is not None:
                kept_lk = lk if kept_lk is None else torch.cat([kept_lk, lk])
            if len(kept_div) > 4 * keep:
                sel = _top(kept_div, keep)
                if kept_lk is not None:
                    sel = torch.unique(torch.cat([sel, _top(kept_lk, keep)]))
                kept_bits, kept_div = kept_bits[sel.numpy()], kept_div[sel]
                kept_lk = None if kept_lk is None else kept_lk[sel]
            done += len(bits)
            sec["model"] += t3 - t2
            sec["scores"] += time.perf_counter() - t3
            if ctx.progress:
                ctx.progress(stage, done, total)
            if ctx.out_of_time(stage):  # the budget: the keys screened so far are the scan
                break
    sel = _top(kept_div, keep)
    if kept_lk is not None:
        sel = torch.unique(torch.cat([sel, _top(kept_lk, keep)]))
    kept_bits = kept_bits[sel.numpy()]
    sec["scan"] = time.perf_counter() - t_start
    sec["scan_cpu"] = time.process_time() - cpu_start
    ctx.counter.evals += done * len(xs)
    ctx.counter.seconds += sec["scan"]
    t0 = time.perf_counter()
    values = ctx.probe_keys(kept_bits, stage)
    sec["rescore"] = time.perf_counter() - t0
    path = "general" if fast is None else ("bf16-chain" if low else "fp32-chain")
    return KeyScan(kept_bits, values, done, len(xs), sec, path)
