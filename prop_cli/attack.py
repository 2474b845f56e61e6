"""`prop attack`: how much of a user's personalization someone without the key can reach.

Threat model and metric names: DESIGN.md. The attacker holds the bundle, not the key.
- T0, black-box keys: the null key, uniform random keys, keys at Hamming distance d from the user's.
- T1, relaxed key: a continuous code in [-1, 1]^n (2u - 1 for u in [0, 1]^n) optimised through the
  encoder, then rounded to a ±1 code and probed too. With the default hashed encoding the encoder's
  input is SHAKE-256(key), so this searches the code space: at least as strong as searching keys
  (a rounded code need not be reachable by any key). With raw encoding the code is the key.
- T2, latent: delta of every keyed layer optimised directly within the encoder's range
  (1 - scale, 1 + scale), skipping the encoder altogether.
- Cross-user: the other users' keys (several key files) on the audited user's behaviour.
The searches maximise divergence from the reference output on the inputs only; they never see the
owner's targets. What they find is then scored against the owner's targets (leakage).

Without a key there are no targets: the audit reports reachable divergence (fidelity) only.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace

import numpy as np
import torch
import torch.nn.functional as F

from . import __version__, metrics
from . import constants as C
from .bundle import Bundle, sha256_file
from .data import Dataset
from .errors import PropError
from .keyed import KeyedModel, key_codes, keys_per_forward

AUDIT_SCHEMA = "prop-audit/1"
SEARCHES = ("relaxed", "latent")
DEFAULT_HAMMING = "1..8"

Progress = Callable[[str, int, int], None]  # (stage, done, total)


@dataclass
class AuditSettings:
    hamming: list[int] | None = None  # None: 1..8 with a key, none without
    per_distance: int = 256  # keys per distance; every key when the neighbourhood is smaller
    random: int = 4096
    search: list[str] = field(default_factory=lambda: list(SEARCHES))
    restarts: int = 8
    search_steps: int = 200
    search_lr: float = 0.1
    samples: int = 256  # samples of --data the audit runs on
    seed: int = 0

    def validate(self, key_bits: int, has_key: bool) -> AuditSettings:
        def need(ok: bool, flag: str, value, rule: str) -> None:
            if not ok:
                raise PropError(f"{flag} {value!r} is invalid", f"{flag} must be {rule}")

        need(self.per_distance >= 1, "--per-distance", self.per_distance, "at least 1")
        need(self.random >= 0, "--random", self.random, ">= 0")
        need(self.restarts >= 1, "--restarts", self.restarts, "at least 1")
        need(self.search_steps >= 1, "--search-steps", self.search_steps, "at least 1")
        need(self.search_lr > 0, "--search-lr", self.search_lr, "positive")
        need(self.samples >= 2, "--samples", self.samples, "at least 2")
        need(
            all(s in SEARCHES for s in self.search),
            "--search",
            ",".join(self.search),
            "relaxed,latent or none",
        )
        if self.hamming:
            if not has_key:
                raise PropError(
                    "--hamming needs the user's key (neighbours are keys a few bits from it)",
                    "pass --key-file, or drop --hamming for a no-key audit",
                )
            top = max(self.hamming)
            need(top <= key_bits, "--hamming", top, f"at most the key size ({key_bits} bits)")
        return self


def parse_hamming(spec: str) -> list[int]:
    """``1..8`` (a range), ``1,2,4`` (a list) or ``3`` -> sorted distinct distances >= 1."""
    bad = PropError(
        f"--hamming {spec!r} is not a distance list",
        "use a range like 1..8, a list like 1,2,4, or one distance like 3 (all >= 1)",
    )
    out: set[int] = set()
    try:
        for part in spec.replace(" ", "").split(","):
            if ".." in part:
                lo, hi = (int(v) for v in part.split(".."))
                if lo > hi:
                    raise bad
                out.update(range(lo, hi + 1))
            else:
                out.add(int(part))
    except ValueError:
        raise bad from None
    if not out or min(out) < 1:
        raise bad
    return sorted(out)


def parse_search(spec: str) -> list[str]:
    """``relaxed,latent`` (any subset) or ``none``."""
    parts = [p for p in spec.replace(" ", "").lower().split(",") if p]
    if parts == ["none"]:
        return []
    if not parts or any(p not in SEARCHES for p in parts):
        raise PropError(
            f"--search {spec!r} is not a search list", "use relaxed, latent, relaxed,latent or none"
        )
    return [s for s in SEARCHES if s in parts]


# --- probe keys ------------------------------------------------------------------------------------


def hamming_keys(user: np.ndarray, d: int, count: int, rng: np.random.Generator) -> np.ndarray:
    """Distinct keys at exactly distance d from ``user``; all of them when there are <= count."""
    n = len(user)
    if math.comb(n, d) <= count:
        from itertools import combinations

        flips = np.zeros((math.comb(n, d), n), dtype=bool)
        for row, pos in enumerate(combinations(range(n), d)):
            flips[row, list(pos)] = True
    else:
        flips = np.zeros((0, n), dtype=bool)
        while len(flips) < count:  # top up after dropping the (rare) duplicates
            pos = np.argsort(rng.random((count - len(flips), n)), axis=1)[:, :d]
            new = np.zeros((len(pos), n), dtype=bool)
            np.put_along_axis(new, pos, True, axis=1)
            flips = np.unique(np.concatenate([flips, new]), axis=0)
        flips = flips[rng.permutation(len(flips))[:count]]
    return (user[None].astype(bool) ^ flips).astype(np.uint8)


# --- evaluation ------------------------------------------------------------------------------------


@dataclass
class _Ref:
    x: torch.Tensor  # inputs the audit runs on
    b: torch.Tensor  # reference output: the original's (or the bundle without a key)
    p: torch.Tensor | None  # the owner's targets; None in a no-key audit
    task: str


def _divergence(o: torch.Tensor, b: torch.Tensor, task: str) -> torch.Tensor:
    """The searches' objective per key (differentiable): mse to b, or KL(softmax b || softmax o)."""
    if task == "classification":
        logp_b = F.log_softmax(b, -1)
        return (logp_b.exp() * (logp_b - F.log_softmax(o, -1))).sum(-1).flatten(1).mean(-1)
    return ((o - b) ** 2).flatten(1).mean(-1)


def _scores(o: torch.Tensor, ref: _Ref) -> dict[str, torch.Tensor]:
    """Per key: fidelity, leakage (with targets) and divergence (the attacker's criterion)."""
    fid = metrics.fidelity(o, ref.b, ref.task)
    out = {
        "fidelity": fid,
        # What the attacker picks restarts by: 1 - agreement (classification), mse (regression).
        "divergence": 1.0 - fid if ref.task == "classification" else fid,
    }
    if ref.p is not None:
        out["leakage"] = metrics.leakage(o, ref.p, ref.b, ref.task)
    return out


def _cat(parts: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    return {k: torch.cat([p[k].detach().cpu() for p in parts]) for k in parts[0]}


class _Counter:
    """Key x sample evaluations and wall time, for the report's speed figures."""

    def __init__(self) -> None:
        self.evals = 0
        self.seconds = 0.0


@torch.inference_mode()
def _probe_codes(
    km: KeyedModel, ref: _Ref, codes: torch.Tensor, stage: str, progress: Progress | None, count: _Counter
) -> dict[str, torch.Tensor]:
    """Score every code (K, n) on every sample, all keys of a chunk in one forward."""
    t0 = time.perf_counter()
    per = keys_per_forward(ref.x.shape[0])
    parts = []
    for i in range(0, len(codes), per):
        deltas = km.layer_deltas(codes[i : i + per].to(ref.x.device))
        parts.append(_scores(km.run_keys(ref.x, deltas), ref))
        if progress:
            progress(stage, min(i + per, len(codes)), len(codes))
    count.evals += len(codes) * ref.x.shape[0]
    count.seconds += time.perf_counter() - t0
    return _cat(parts)


@torch.inference_mode()
def _probe_deltas(km: KeyedModel, ref: _Ref, deltas: list[torch.Tensor]) -> dict[str, torch.Tensor]:
    return _cat([_scores(km.run_keys(ref.x, deltas), ref)])


# --- white-box searches --------------------------------------------------------------------------


def _optimise(
    params: list[torch.Tensor],
    make_deltas: Callable[[], list[torch.Tensor]],
    km: KeyedModel,
    ref: _Ref,
    steps: int,
    lr: float,
    stage: str,
    progress: Progress | None,
) -> None:
    """Adam on all restarts at once (each restart is one key row); maximise each one's divergence."""
    opt = torch.optim.Adam(params, lr=lr)
    for step in range(steps):
        div = _divergence(km.run_keys(ref.x, make_deltas()), ref.b, ref.task)
        opt.zero_grad(set_to_none=True)
        (-div.sum()).backward()  # restarts are independent: the sum's gradient is each one's own
        opt.step()
        if progress and (step % 10 == 9 or step == steps - 1):
            progress(stage, step + 1, steps)


def _relaxed_search(
    km: KeyedModel, ref: _Ref, s: AuditSettings, gen: torch.Generator, progress: Progress | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """T1: relaxed codes (R, n) in (-1, 1) and their rounding to ±1."""
    n = km.encoder.code_bits
    u = torch.rand(s.restarts, n, generator=gen).clamp(0.02, 0.98)
    theta = torch.logit(u).to(ref.x.device).requires_grad_(True)

    def codes() -> torch.Tensor:
        return torch.tanh(theta / 2)  # = 2 * sigmoid(theta) - 1: the relaxed key u mapped to ±1

    _optimise(
        [theta],
        lambda: km.layer_deltas(codes()),
        km,
        ref,
        s.search_steps,
        s.search_lr,
        "relaxed",
        progress,
    )
    relaxed = codes().detach()
    return relaxed, torch.where(relaxed >= 0, 1.0, -1.0)


def _latent_search(
    km: KeyedModel, ref: _Ref, s: AuditSettings, gen: torch.Generator, progress: Progress | None
) -> list[torch.Tensor]:
    """T2: delta per keyed layer (R, d_i) optimised directly, within the encoder's range."""
    scale = km.encoder.scale
    phis = [
        torch.randn(s.restarts, d, generator=gen).to(ref.x.device).requires_grad_(True)
        for d in km.encoder.features
    ]

    def deltas() -> list[torch.Tensor]:
        return [1.0 + scale * torch.tanh(p) for p in phis]

    _optimise(phis, deltas, km, ref, s.search_steps, s.search_lr, "latent", progress)
    return [d.detach() for d in deltas()]


# --- the audit -------------------------------------------------------------------------------------


def _summary(v: dict[str, torch.Tensor], task: str) -> dict:
    worst_fid = "min" if task == "classification" else "max"
    return {
        "keys": int(len(v["fidelity"])),
        "leakage": metrics.summarize(v["leakage"], "max") if "leakage" in v else None,
        "fidelity": metrics.summarize(v["fidelity"], worst_fid),
    }


def _group(name: str, threat: str, v: dict, task: str, *, is_key: bool, distance: int | None = None) -> dict:
    return {"name": name, "threat": threat, "distance": distance, "is_key": is_key, **_summary(v, task)}


def _search_group(name: str, threat: str, v: dict, task: str, s: AuditSettings, is_key: bool) -> dict:
    g = _group(name, threat, v, task, is_key=is_key)
    best = int(torch.argmax(v["divergence"]))  # the attacker's pick: it cannot see the targets
    g["search"] = {
        "restarts": s.restarts,
        "steps": s.search_steps,
        "best_restart": best,
        "best_divergence": float(v["divergence"][best]),
        "best_leakage": float(v["leakage"][best]) if "leakage" in v else None,
        "best_fidelity": float(v["fidelity"][best]),
        "divergence": [float(d) for d in v["divergence"]],
        "leakage": [float(d) for d in v["leakage"]] if "leakage" in v else None,
    }
    return g


def _pick_samples(data: Dataset, n: int, seed: int) -> np.ndarray:
    order = np.random.default_rng(seed).permutation(len(data))
    return np.sort(order[: min(n, len(data))])


def audit(
    bundle: Bundle,
    data: Dataset,
    keys: list[np.ndarray],
    settings: AuditSettings,
    *,
    original: torch.nn.Module | None = None,
    device: str = "cpu",
    progress: Progress | None = None,
) -> dict:
    """Run the audit; returns the report (schema ``prop-audit/1``, documented in the README).

    ``keys[0]`` is the audited user's key (their targets are ``data.y``), ``keys[1:]`` other users'
    keys; no keys = a no-key audit. ``original`` is the reference b (default: the bundle, no key).
    """
    from .trainer import check_compatible, resolve_device

    started = time.perf_counter()
    task = bundle.task
    has_key = bool(keys)
    s = replace(settings)  # the caller's settings stay as given
    if s.hamming is None:
        s.hamming = parse_hamming(DEFAULT_HAMMING) if has_key else []
    s.validate(bundle.key_bits, has_key)
    if has_key and data.y is None:
        raise PropError(
            f"--data {data.path} has no field 'y': leakage needs the owner's targets",
            "pass the data the bundle was personalized with (x and y), or drop --key-file",
        )
    if data.y is not None and data.task != task:
        raise PropError(
            f"--data {data.path}: y holds {data.task} targets but the bundle is a {task} bundle",
            "pass the data the bundle was personalized with",
        )
    check_compatible(bundle.loaded, data, "--data")
    for i, k in enumerate(keys):
        if len(k) != bundle.key_bits:
            raise PropError(
                f"key {i + 1} has {len(k)} bits but the bundle expects {bundle.key_bits}",
                "use the keys the bundle was personalized with",
            )

    dev = resolve_device(device)
    km = bundle.keyed.to(dev).eval()
    grad_flags = [p.requires_grad for p in km.parameters()]
    km.requires_grad_(False)  # searches need gradients w.r.t. their own variables only
    idx = _pick_samples(data, s.samples, s.seed)
    x = torch.from_numpy(data.x[idx]).to(dev)
    with torch.inference_mode():
        b = (original.to(dev).eval() if original is not None else km.module)(x)
    p = None
    if has_key:
        p = torch.from_numpy(data.y[idx]).to(dev)
        if task == "regression" and p.dim() == 1:
            p = p[:, None]
    ref = _Ref(x, b.clone(), p, task)  # clone: out of inference mode, usable next to autograd
    rng = np.random.default_rng(s.seed)
    gen = torch.Generator().manual_seed(s.seed)
    enc = bundle.key_encoding
    count = _Counter()
    timing: dict[str, float] = {}
    groups: list[dict] = []

    def timed(stage: str, fn):
        t0 = time.perf_counter()
        r = fn()
        timing[stage] = timing.get(stage, 0.0) + time.perf_counter() - t0
        return r

    try:
        user = None
        if has_key:
            with torch.inference_mode():
                o_user = km.run_keys(x, km.layer_deltas(key_codes(keys[0], enc).to(dev)))
                v = _scores(o_user, ref)
            user = {
                "personalization": metrics.personalization(o_user[0], p, b, task),
                "leakage": float(v["leakage"][0]),
                "fidelity": float(v["fidelity"][0]),
            }
        with torch.inference_mode():
            ones = [torch.ones(1, f, device=dev) for f in km.encoder.features]
            null = timed("null", lambda: _probe_deltas(km, ref, ones))
        groups.append(_group("null", "T0", null, task, is_key=True))
        if s.random:
            rand = rng.integers(0, 2, (s.random, bundle.key_bits), dtype=np.uint8)
            v = timed(
                "random", lambda: _probe_codes(km, ref, key_codes(rand, enc), "random", progress, count)
            )
            groups.append(_group("random", "T0", v, task, is_key=True))
        for d in s.hamming:
            near = hamming_keys(keys[0], d, s.per_distance, rng)
            v = timed(
                "hamming",
                lambda near=near, d=d: _probe_codes(
                    km, ref, key_codes(near, enc), f"hamming {d}", progress, count
                ),
            )
            groups.append(_group(f"hamming {d}", "T0", v, task, is_key=True, distance=d))
        if "relaxed" in s.search:
            relaxed, rounded = timed("relaxed", lambda: _relaxed_search(km, ref, s, gen, progress))
            v = _probe_codes(km, ref, relaxed, "relaxed", None, count)
            groups.append(_search_group("relaxed", "T1", v, task, s, is_key=False))
            v = _probe_codes(km, ref, rounded, "relaxed", None, count)
            g = _search_group("relaxed-rounded", "T1", v, task, s, is_key=enc == "raw")
            if has_key:  # 0 = the search found the user's own code (for raw encoding: the key)
                user_code = key_codes(keys[0], enc).to(rounded.device)
                g["search"]["code_distance"] = [int(c) for c in (rounded != user_code).sum(1)]
            groups.append(g)
        if "latent" in s.search:
            deltas = timed("latent", lambda: _latent_search(km, ref, s, gen, progress))
            groups.append(_search_group("latent", "T2", _probe_deltas(km, ref, deltas), task, s, False))
        for j, k in enumerate(keys[1:], start=2):
            v = _probe_codes(km, ref, key_codes(k, enc), f"user {j}", None, count)
            groups.append(_group(f"user {j}", "cross-user", v, task, is_key=True))
    finally:
        for prm, flag in zip(km.parameters(), grad_flags):
            prm.requires_grad_(flag)

    return {
        "schema": AUDIT_SCHEMA,
        "prop_version": __version__,
        "mode": "owner" if has_key else "no-key",
        "bundle": {
            "path": str(bundle.path),
            "manifest_sha256": sha256_file(bundle.path / C.MANIFEST),
            "task": task,
            "key_bits": bundle.key_bits,
            "key_encoding": enc,
            "keyed_layers": bundle.manifest[C.M_KEYED_LAYERS],
        },
        "data": {"path": str(data.path), "rows": len(data), "samples": int(len(idx))},
        "reference": "original" if original is not None else "bundle-no-key",
        "settings": {**asdict(s), "other_users": max(0, len(keys) - 1), "device": str(dev)},
        "user": user,
        "groups": groups,
        "speed": {
            "key_sample_evaluations": count.evals,
            "evaluations_per_second": count.evals / count.seconds if count.seconds else None,
            "stage_seconds": timing,
            "wall_seconds": time.perf_counter() - started,
        },
    }


def leak_failures(report: dict, threshold: float) -> list[tuple[str, float]]:
    """(group, worst-key leakage) for every probe group above ``threshold``."""
    return [
        (g["name"], g["leakage"]["worst"])
        for g in report["groups"]
        if g["leakage"] is not None and g["leakage"]["worst"] > threshold
    ]


def apply_max_leak(report: dict, threshold: float) -> list[tuple[str, float]]:
    """Add the --max-leak verdict to the report; returns the failing groups."""
    if report["user"] is None:
        raise PropError("--max-leak needs the user's key and targets", "pass --key-file with --data x,y")
    if not 0 <= threshold <= 1:
        raise PropError(f"--max-leak {threshold} is out of range", "use a leakage in [0, 1], e.g. 0.02")
    failing = leak_failures(report, threshold)
    report["max_leak"] = {"threshold": threshold, "passed": not failing, "failing": [n for n, _ in failing]}
    return failing


def load_original(bundle: Bundle, path: str) -> torch.nn.Module:
    """The original checkpoint as the reference b, rebuilt the way the bundle's base is."""
    import prop_adapters
    from prop_adapters import read_weights

    weights, _ = read_weights(path)
    try:
        return prop_adapters.rebuild(bundle.manifest[C.M_MODEL], weights, str(path)).module.eval()
    except (RuntimeError, KeyError, ValueError) as e:
        raise PropError(
            f"--original {path} does not fit the bundle's model ({type(e).__name__})",
            "pass the checkpoint the bundle was personalized from",
        ) from None
