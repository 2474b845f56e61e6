"""Attacks on an unsealed bundle's KeyedModel, for benchmarks/bench_harden.py (issue 9, part 3).

Ported from the issue-9 research scripts; kept here, outside prop_cli, on purpose: the audit's own
probes live in prop_cli/probes. Every attack returns candidates (codes or deltas); ``Ref`` scores them
against the ORIGINAL's outputs b and the owner's targets p. The attacker never sees p: its pick is
the candidate with the highest divergence from b on the inputs.

Controls (a probe run where the bundle gives nothing) are the caller's: the searches and structure
attacks run again on a bundle that holds nothing of the user (bench_harden trains one); few-shot
code/delta fits are compared with ``fewshot_control``, fine-tuning the original on the same samples.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from prop_cli.core import metrics
from prop_cli.core.key_sampling import neighbours_at
from prop_cli.core.keyed_model import KeyedModel, KeyEncoder, key_codes


@dataclass
class Ref:
    """Scoring inputs x, the original's outputs b on them, the owner's targets p."""

    x: torch.Tensor
    b: torch.Tensor
    p: torch.Tensor
    task: str


def divergence(o: torch.Tensor, b: torch.Tensor, task: str) -> torch.Tensor:
    """The attacker's criterion per key, no targets needed: 1 - agreement, or mse to b."""
    f = metrics.fidelity(o, b, task)
    return 1.0 - f if task == "classification" else f


def smooth_divergence(o: torch.Tensor, b: torch.Tensor, task: str) -> torch.Tensor:
    """Differentiable divergence per key (K, B, ...) -> (K,): KL from b's softmax, or mse."""
    if task == "classification":
        logp = F.log_softmax(b, -1)
        return (logp.exp() * (logp - F.log_softmax(o, -1))).sum(-1).flatten(1).mean(-1)
    return ((o - b) ** 2).flatten(1).mean(-1)


@torch.no_grad()
def score_codes(km: KeyedModel, ref: Ref, codes: torch.Tensor, chunk: int = 64) -> dict[str, torch.Tensor]:
    lk, dv = [], []
    for i in range(0, len(codes), chunk):
        o = km.run_keys(ref.x, km.layer_deltas(codes[i : i + chunk]))
        lk.append(metrics.leakage(o, ref.p, ref.b, ref.task))
        dv.append(divergence(o, ref.b, ref.task))
    return {"leakage": torch.cat(lk), "divergence": torch.cat(dv)}


@torch.no_grad()
def score_deltas(km: KeyedModel, ref: Ref, deltas: list[torch.Tensor]) -> dict[str, torch.Tensor]:
    o = km.run_keys(ref.x, deltas)
    return {
        "leakage": metrics.leakage(o, ref.p, ref.b, ref.task),
        "divergence": divergence(o, ref.b, ref.task),
    }


def pick(scores: dict[str, torch.Tensor]) -> float:
    """Leakage of the attacker's pick: the candidate that moves the outputs most."""
    return float(scores["leakage"][int(torch.argmax(scores["divergence"]))])


# ---------------------------------------------------------------------------------------------- keys


def hamming_worst(
    km: KeyedModel, ref: Ref, key: np.ndarray, encoding: str, per: int = 128
) -> dict[int, float]:
    """Worst leakage among ``per`` keys at each Hamming distance 1..8 from the user's key."""
    rng = np.random.default_rng(7)
    out = {}
    for d in range(1, 9):
        codes = key_codes(neighbours_at(key, d, per, rng), encoding)
        out[d] = float(score_codes(km, ref, codes)["leakage"].max())
    return out


def random_scan(
    km: KeyedModel, ref: Ref, n_keys: int, encoding: str, screen: int = 32, chunk: int = 4096, top: int = 128,
    seed: int = 11, bf16: bool = True,
) -> dict:  # fmt: skip
    """Black box at scale: ``n_keys`` random keys, streamed in chunks. Each chunk is screened on
    ``screen`` samples (bfloat16 autocast), keeping the top keys by screening leakage and by
    divergence; the kept keys are re-scored exactly (float32, every sample of ``ref``)."""
    rng = np.random.default_rng(seed)
    bits = km.encoder.code_bits
    xs, bs, ps = ref.x[:screen], ref.b[:screen], ref.p[:screen]
    keep = torch.zeros(0, bits)
    keep_lk, keep_dv = torch.zeros(0), torch.zeros(0)
    t0 = time.perf_counter()
    done = 0
    with torch.inference_mode(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
        while done < n_keys:
            k = min(chunk, n_keys - done)
            codes = key_codes(rng.integers(0, 2, (k, bits), dtype=np.uint8), encoding)
            o = km.run_keys(xs, km.layer_deltas(codes)).float()
            keep = torch.cat([keep, codes])
            keep_lk = torch.cat([keep_lk, metrics.leakage(o, ps, bs, ref.task)])
            keep_dv = torch.cat([keep_dv, divergence(o, bs, ref.task)])
            if len(keep) > 4 * top:
                sel = torch.unique(torch.cat([keep_lk.topk(top).indices, keep_dv.topk(top).indices]))
                keep, keep_lk, keep_dv = keep[sel], keep_lk[sel], keep_dv[sel]
            done += k
    seconds = time.perf_counter() - t0
    exact = score_codes(km, ref, keep)
    return {
        "keys": n_keys,
        "seconds": seconds,
        "keys_per_s": n_keys / seconds,
        "worst": float(exact["leakage"].max()),
        "pick": pick(exact),
    }


# ----------------------------------------------------------------------------------- T1 relaxed search


def relaxed_search(
    km: KeyedModel, ref: Ref, restarts: int, steps: int, lr: float, seed: int = 0
) -> torch.Tensor:
    """T1: relaxed codes in [-1, 1]^n (tanh of free parameters), Adam on each restart's divergence."""
    gen = torch.Generator().manual_seed(seed)
    theta = torch.logit(torch.rand(restarts, km.encoder.code_bits, generator=gen).clamp(0.02, 0.98))
    theta.requires_grad_(True)
    opt = torch.optim.Adam([theta], lr=lr)
    for _ in range(steps):
        div = smooth_divergence(km.run_keys(ref.x, km.layer_deltas(torch.tanh(theta / 2))), ref.b, ref.task)
        opt.zero_grad(set_to_none=True)
        (-div.sum()).backward()
        opt.step()
    return torch.tanh(theta.detach() / 2)


def t1(km: KeyedModel, ref: Ref, restarts: int, steps: int, lrs=(0.1, 1.0)) -> dict:
    """Attacker's pick over each search's relaxed codes and their roundings; the worse lr counts."""
    out = {"pick": 0.0, "max": 0.0}
    for lr in lrs:
        relaxed = relaxed_search(km, ref, restarts, steps, lr)
        for codes in (relaxed, torch.where(relaxed >= 0, 1.0, -1.0)):
            sc = score_codes(km, ref, codes)
            out["pick"] = max(out["pick"], pick(sc))
            out["max"] = max(out["max"], float(sc["leakage"].max()))
    return out


# -------------------------------------------------------------------------------- structure (no data)


def _linears(enc: KeyEncoder) -> list[torch.nn.Linear]:
    return [m for m in enc.net if isinstance(m, torch.nn.Linear)]


def _both(dirs: torch.Tensor) -> torch.Tensor:
    """Each direction and its negation as ±1 codes (a singular vector's sign is arbitrary)."""
    s = torch.where(dirs >= 0, 1.0, -1.0)
    return torch.cat([s, -s])


@torch.no_grad()
def cands_init_diff(km: KeyedModel, seed: int, k: int = 3) -> torch.Tensor:
    """W1 - W1_init, the init recreated as the trainer makes it from the manifest's seed."""
    enc = km.encoder
    torch.manual_seed(seed)
    init = KeyEncoder(enc.code_bits, enc.features, [m.out_features for m in _linears(enc)][:-1], enc.scale)
    return _both(torch.linalg.svd(_linears(enc)[0].weight - _linears(init)[0].weight).Vh[:k])


@torch.no_grad()
def cands_w1_svd(km: KeyedModel, k: int = 3) -> torch.Tensor:
    """Top singular directions of the first layer (raw, row-centred, column-centred): init unknown."""
    w = _linears(km.encoder)[0].weight
    mats = (w, w - w.mean(1, keepdim=True), w - w.mean(0, keepdim=True))
    return _both(torch.cat([torch.linalg.svd(m, full_matrices=False).Vh[:k] for m in mats]))


@torch.no_grad()
def cands_head(km: KeyedModel, k: int = 3) -> torch.Tensor:
    """The head starts at zero: its top hidden directions, pulled back through W1, give the code."""
    lins = _linears(km.encoder)
    if len(lins) != 2:
        return torch.zeros(0, km.encoder.code_bits)
    first, last = lins
    vh = torch.linalg.svd(last.weight, full_matrices=False).Vh[:k]
    h0 = torch.tanh(first.bias)
    return _both(torch.cat([vh @ first.weight, (vh * (1 - h0**2)) @ first.weight]))


def cands_jacobian(km: KeyedModel, points: int = 4, k: int = 2) -> torch.Tensor:
    """Top right singular vectors of d(head input)/d(code) at the zero code and random codes."""
    enc = km.encoder
    gen = torch.Generator().manual_seed(0)
    at = torch.cat([torch.zeros(1, enc.code_bits), torch.rand(points, enc.code_bits, generator=gen) * 2 - 1])
    dirs = [torch.linalg.svd(torch.func.jacrev(lambda z: enc.net(z[None])[0])(c)).Vh[:k] for c in at]
    return _both(torch.cat(dirs))


def cands_latent_norm(km: KeyedModel, restarts: int = 32, steps: int = 200, lr: float = 0.1) -> torch.Tensor:
    """Data-free search: relaxed codes that maximise the head's output norm (delta far from 1)."""
    enc = km.encoder
    gen = torch.Generator().manual_seed(0)
    theta = torch.logit(torch.rand(restarts, enc.code_bits, generator=gen).clamp(0.02, 0.98))
    theta.requires_grad_(True)
    opt = torch.optim.Adam([theta], lr=lr)
    for _ in range(steps):
        obj = (torch.tanh(enc.net(torch.tanh(theta / 2))) ** 2).sum()
        opt.zero_grad(set_to_none=True)
        (-obj).backward()
        opt.step()
    c = torch.tanh(theta.detach() / 2)
    return torch.cat([c, torch.where(c >= 0, 1.0, -1.0)])


@torch.no_grad()
def deltas_head(km: KeyedModel, k: int = 3, alphas=(0.5, 1, 2, 4, 8, 16, 32)) -> list[torch.Tensor]:
    """No code at all: delta = 1 + s tanh(alpha u + b) along the head's top output directions u."""
    enc = km.encoder
    last = _linears(enc)[-1]
    u = torch.linalg.svd(last.weight, full_matrices=False).U[:, :k].T
    dirs = torch.cat([u, -u])
    a = torch.tensor(alphas, dtype=torch.float32)
    pre = (a[:, None, None] * dirs[None]).reshape(-1, dirs.shape[1]) + last.bias[None]
    return list((1.0 + enc.scale * torch.tanh(pre)).split(enc.features, dim=1))


def structure(km: KeyedModel, ref: Ref, seed: int) -> dict[str, float]:
    """Attacker's pick per structure attack (weights and derivatives only, no data, no search)."""
    attacks = {
        "init_diff": lambda: cands_init_diff(km, seed),
        "w1_svd": lambda: cands_w1_svd(km),
        "head": lambda: cands_head(km),
        "jacobian": lambda: cands_jacobian(km),
        "latent_norm": lambda: cands_latent_norm(km),
    }
    out = {}
    for name, fn in attacks.items():
        codes = fn()
        out[name] = pick(score_codes(km, ref, codes)) if len(codes) else 0.0
    out["head_delta"] = pick(score_deltas(km, ref, deltas_head(km)))
    return out


# ------------------------------------------------------------------------------------------ few-shot


def _fit_loss(o: torch.Tensor, y: torch.Tensor, task: str) -> torch.Tensor:
    """Per key (K, k, ...) -> (K,): the attacker's loss on its k labelled samples."""
    if task == "classification":
        return (
            F.cross_entropy(o.flatten(0, 1), y.repeat(o.shape[0]), reduction="none")
            .view(o.shape[0], -1)
            .mean(1)
        )
    return ((o - y[None]) ** 2).flatten(1).mean(1)


def _fit(params: list[torch.Tensor], run, y: torch.Tensor, task: str, steps: int, lr: float) -> int:
    opt = torch.optim.Adam(params, lr=lr)
    for _ in range(steps):
        loss = _fit_loss(run(), y, task)
        opt.zero_grad(set_to_none=True)
        loss.sum().backward()
        opt.step()
    with torch.no_grad():
        return int(torch.argmin(_fit_loss(run(), y, task)))


def fewshot_code(km: KeyedModel, xk, yk, task: str, restarts: int = 8, steps: int = 200) -> torch.Tensor:
    """T3 (code): relaxed codes fitted through the encoder to k samples; the best-fitting one."""
    gen = torch.Generator().manual_seed(0)
    theta = torch.logit(torch.rand(restarts, km.encoder.code_bits, generator=gen).clamp(0.02, 0.98))
    theta.requires_grad_(True)
    best = _fit(
        [theta], lambda: km.run_keys(xk, km.layer_deltas(torch.tanh(theta / 2))), yk, task, steps, 0.1
    )
    return torch.tanh(theta.detach()[best : best + 1] / 2)


def fewshot_delta(
    km: KeyedModel, xk, yk, task: str, restarts: int = 4, steps: int = 200
) -> list[torch.Tensor]:
    """T3 (delta): the keyed layers' deltas fitted directly to k samples (encoder skipped)."""
    gen = torch.Generator().manual_seed(0)
    s = km.encoder.scale
    phis = []
    for d in km.encoder.features:
        p = torch.randn(restarts, d, generator=gen) * 0.5
        p[0] = 0  # one restart from delta = 1, the no-key model
        phis.append(p.requires_grad_(True))
    best = _fit(phis, lambda: km.run_keys(xk, [1.0 + s * torch.tanh(p) for p in phis]), yk, task, steps, 0.05)
    return [(1.0 + s * torch.tanh(p[best : best + 1])).detach() for p in phis]


def fewshot_control(original: torch.nn.Module, xk, yk, task: str, steps: int = 200) -> torch.nn.Module:
    """T3's control: fine-tune every weight of the original on the same k samples."""
    m = copy.deepcopy(original).train().requires_grad_(True)
    _fit(list(m.parameters()), lambda: m(xk)[None], yk, task, steps, 1e-3)
    return m.eval().requires_grad_(False)


def fewshot(km: KeyedModel, original: torch.nn.Module, ref: Ref, x, y, ks=(1, 4, 16, 64)) -> dict[int, dict]:
    """Leakage on ``ref`` after fitting k of the user's samples: code fit, delta fit, control."""
    out = {}
    for k in ks:
        idx = torch.from_numpy(np.random.default_rng(1000 + k).choice(len(x), k, replace=False))
        xk, yk = x[idx], y[idx]
        tuned = fewshot_control(original, xk, yk, ref.task)
        with torch.no_grad():
            ctrl = tuned(ref.x)[None]
        out[k] = {
            "code": float(score_codes(km, ref, fewshot_code(km, xk, yk, ref.task))["leakage"][0]),
            "delta": float(score_deltas(km, ref, fewshot_delta(km, xk, yk, ref.task))["leakage"][0]),
            "control": float(metrics.leakage(ctrl, ref.p, ref.b, ref.task)[0]),
        }
    return out
