"""`prop attack`: how much of a user's personalization someone holding the bundle, not the key, reaches.

This module runs the registered probes (``probes``) and their controls on what ``target`` chooses,
and assembles the report (schema ``prop-audit/2``, documented in docs/audit.md) with the
``--max-leak`` gate. Threat model: docs/threat-model.md; metrics: docs/metrics.md. Probes score
against the owner's targets only after the fact; searches optimise on the inputs alone.
"""

from __future__ import annotations

import time
from dataclasses import asdict, replace

import numpy as np
import torch

from prop_cli import __version__
from prop_cli import constants as C
from prop_cli.bundle import Bundle
from prop_cli.config import AuditSettings, parse_hamming
from prop_cli.core import metrics
from prop_cli.core.device import resolve_device
from prop_cli.core.keyed_model import KeyedModel
from prop_cli.datasources import Dataset
from prop_cli.datasources.fit import prepare
from prop_cli.errors import PropError
from prop_cli.files import sha256_file

from . import probes, target
from .probes.base import Counter, Group, ProbeContext, Progress, Reference

DEFAULT_HAMMING = "1..8"
# Below this leakage of the user's own key, its personalization is at the base's level (fix for a
# wrong key file, or data the bundle was not personalized on, going unnoticed).
WRONG_KEY_LEAKAGE = 0.5
# Per-candidate lists in a search's JSON only up to this many candidates (a key scan keeps hundreds).
PER_RESTART_LISTS = 256
MAX_SHOTS = 64  # the largest few-shot k
SATURATED = 0.99  # a control's worst leakage at or above this cannot separate the bundle from the original


def _sample_index(data: Dataset, n: int, seed: int) -> np.ndarray:
    order = np.random.default_rng(seed).permutation(len(data))
    return np.sort(order[: min(n, len(data))])


def _shots(data: Dataset, audit_rows: np.ndarray, seed: int, dev, reference, task: str) -> Reference | None:
    """Up to MAX_SHOTS labelled rows outside the audit sample: what a few-shot attacker holds."""
    rest = np.setdiff1d(np.arange(len(data)), audit_rows)
    if not len(rest):
        return None
    rows = np.random.default_rng([seed, 1]).permutation(rest)[:MAX_SHOTS]
    x = torch.from_numpy(data.x[rows]).to(dev)
    p = torch.from_numpy(data.y[rows]).to(dev)
    if task == "regression" and p.dim() == 1:
        p = p[:, None]
    with torch.inference_mode():
        b = reference(x)
    return Reference(x, b.clone(), p, task)


def _control_model(
    bundle: Bundle, km: KeyedModel, original: torch.nn.Module | None
) -> tuple[KeyedModel | None, str]:
    """The original checkpoint keyed like the bundle (the controls' model), or why there is none."""
    if original is not None:
        where = "the original checkpoint (--original)"
    else:
        original, where = target.default_original(bundle, km)
        if original is None:
            return None, where
    mods = dict(original.named_modules())
    base = dict(km.module.named_modules())
    if not all(n in mods and mods[n].weight.shape == base[n].weight.shape for n in km.layer_names):
        return None, "the original module does not have the bundle's keyed layers (names and shapes)"
    module = target.unhooked_copy(original).to(km.encoder.net[0].weight.device).eval()
    return km.on(module).eval(), where


def _summary(v: dict[str, torch.Tensor], task: str) -> dict:
    worst_fid = "min" if task == "classification" else "max"
    return {
        "keys": int(len(v["fidelity"])),
        "leakage": metrics.summarize(v["leakage"], "max") if "leakage" in v else None,
        "fidelity": metrics.summarize(v["fidelity"], worst_fid),
    }


def _search(v: dict[str, torch.Tensor], info: dict) -> dict:
    best = int(torch.argmax(v["divergence"]))  # the attacker's pick: it cannot see the targets
    return {
        **info,
        "best_restart": best,
        "best_divergence": float(v["divergence"][best]),
        "best_leakage": float(v["leakage"][best]) if "leakage" in v else None,
        "best_fidelity": float(v["fidelity"][best]),
        **_per_restart(v),
    }


def _per_restart(v: dict[str, torch.Tensor]) -> dict:
    if len(v["divergence"]) > PER_RESTART_LISTS:
        return {}
    return {
        "divergence": [float(d) for d in v["divergence"]],
        "leakage": [float(d) for d in v["leakage"]] if "leakage" in v else None,
    }


def _group_json(g: Group, task: str) -> dict:
    out = {"name": g.name, "distance": g.distance, "is_key": g.is_key, **_summary(g.values, task)}
    if g.search is not None:
        out["search"] = _search(g.values, g.search)
    return out


def _with_control(row: dict, probe: probes.Probe, control: dict | None) -> dict:
    """Add the control and the gated value: raw worst-key leakage for key probes and for searches without
    a control; leakage beyond the control (bundle - control, at least 0) for searches with one."""
    row.update(
        probe=probe.name, threat=probe.threat, kind=probe.kind, control=control, beyond=None, gate=None
    )
    lk = row["leakage"]
    if lk is None:
        return row
    if control is not None and control.get("available") and control["leakage"] is not None:
        row["beyond"] = max(0.0, lk["worst"] - control["leakage"]["worst"])
    if probe.kind == "search" and row["beyond"] is not None:
        row["gate"] = {"on": "beyond-control", "value": row["beyond"]}
    else:
        row["gate"] = {"on": "raw", "value": lk["worst"]}
    return row


def _settings(settings: AuditSettings, bundle: Bundle, has_key: bool) -> AuditSettings:
    s = replace(settings)  # the caller's settings stay as given
    if s.hamming is None:
        s.hamming = parse_hamming(DEFAULT_HAMMING) if has_key else []
    s.validate(bundle.key_bits, has_key, probes.names())
    chosen = probes.select(s.probes)
    if not has_key:
        needing = [p for p in chosen if probes.probe_named(p).needs == "key"]
        if s.probes is not None and needing:
            raise PropError(
                f"--probes {','.join(needing)} need the user's key",
                "pass --key-file, or leave those probes out of a no-key audit",
            )
        chosen = [p for p in chosen if p not in needing]
    s.probes = chosen
    return s


def _check_inputs(bundle: Bundle, data: Dataset, keys: list[np.ndarray]) -> Dataset:
    if keys and data.y is None:
        raise PropError(
            f"--data {data.path} has no field 'y': leakage needs the owner's targets",
            "pass the data the bundle was personalized with (x and y), or drop --key-file",
        )
    for i, k in enumerate(keys):
        bundle.check_key(k, f"key {i + 1}")
    data, _ = prepare(bundle.loaded, data, "--data", bundle.task)
    return data


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
    """Run the audit; returns the report (schema ``prop-audit/2``, documented in docs/audit.md).

    ``keys[0]`` is the audited user's key (their targets are ``data.y``), ``keys[1:]`` other users'
    keys; no keys = a no-key audit. ``original`` is the original checkpoint's module: the reference b
    (default: the bundle without a key) and the model the controls run on. A policy bundle is audited
    as an array model: pass it and its data through ``target.as_array`` first.
    """
    started = time.perf_counter()
    task = bundle.task
    has_key = bool(keys)
    s = _settings(settings, bundle, has_key)
    data = _check_inputs(bundle, data, keys)

    dev = resolve_device(device)
    km = target.attacked_model(bundle, dev)
    grad_flags = [p.requires_grad for p in km.parameters()]
    km.requires_grad_(False)  # searches need gradients w.r.t. their own variables only
    idx = _sample_index(data, s.samples, s.seed)
    x = torch.from_numpy(data.x[idx]).to(dev)
    with torch.inference_mode():
        b = (original.to(dev).eval() if original is not None else km.module)(x)
    p = None
    if has_key:
        p = torch.from_numpy(data.y[idx]).to(dev)
        if task == "regression" and p.dim() == 1:
            p = p[:, None]
    shots = (
        _shots(data, idx, s.seed, x.device, km.module if original is None else original, task)
        if has_key
        else None
    )
    control_km, control_from = _control_model(bundle, km, original)
    ref = Reference(x, b.clone(), p, task)  # clone: out of inference mode, usable next to autograd
    counter = Counter()
    seed = bundle.manifest.get(C.M_CONFIG, {}).get("seed")
    ctx = ProbeContext(km, ref, s, list(keys), bundle.key_encoding, control_km, progress, counter,
                       shots=shots, seed_hint=seed if isinstance(seed, int) else None)  # fmt: skip
    ctx = target.probe_context(bundle, ctx)
    timing: dict[str, float] = {}
    groups: list[dict] = []
    user, warnings = None, []
    try:
        if has_key:
            user = _user(ctx, keys[0])
            warnings += _enrolment(bundle, keys[0])
            if user["leakage"] < WRONG_KEY_LEAKAGE:
                warnings.append(
                    f"the key shows little of the personalization (leakage of your own key "
                    f"{user['leakage']:.2f}, personalization {user['personalization']:.2f}): it may not be "
                    f"this bundle's key, or --data not the data it was personalized on"
                )
        for name in s.probes:
            probe = probes.probe_named(name)
            if probe.needs == "other-keys" and len(keys) < 2:
                continue
            t0 = time.perf_counter()
            found = probe.run(replace(ctx, probe=name))
            controls = _controls(probe, ctx, control_km, control_from, name, task, found)
            timing[name] = time.perf_counter() - t0
            for g in found:
                control = None if controls is None else controls.get(g.name, controls.get(None))
                groups.append(_with_control(_group_json(g, task), probe, control))
    finally:
        for prm, flag in zip(km.parameters(), grad_flags):
            prm.requires_grad_(flag)
    if target.controls_can_saturate(bundle):
        warnings += _saturated_controls(groups, user)

    return {
        "schema": C.AUDIT_SCHEMA,
        "prop_version": __version__,
        "mode": "owner" if has_key else "no-key",
        "bundle": {
            "path": str(bundle.path),
            "manifest_sha256": sha256_file(bundle.path / C.MANIFEST),
            "task": task,
            "key_bits": bundle.key_bits,
            "key_encoding": bundle.key_encoding,
            "sealed": bundle.is_sealed,
            "keyed_layers": bundle.manifest[C.M_KEYED_LAYERS],
        },
        "data": {"path": str(data.path), "rows": len(data), "samples": int(len(idx))},
        "reference": "original" if original is not None else "bundle-no-key",
        "control_model": control_from if control_km is not None else None,
        "settings": {**asdict(s), "other_users": max(0, len(keys) - 1), "device": str(dev)},
        "user": user,
        "warnings": warnings,
        "groups": groups,
        "speed": {
            "key_sample_evaluations": counter.evals,
            "evaluations_per_second": counter.evals / counter.seconds if counter.seconds else None,
            "stage_seconds": timing,
            "blackbox": _scan_speed(groups),
            "wall_seconds": time.perf_counter() - started,
        },
    }


def _enrolment(bundle: Bundle, key: np.ndarray) -> list[str]:
    """The audit measures the method for any key; say whether prop run would run this key at all."""
    try:
        if bundle.mode.enrolled(key):
            return []
        return [f"{bundle.mode.not_enrolled(str(bundle.path))}: prop run gives the base for it"]
    except PropError as e:
        return [e.what]


def _saturated_controls(groups: list[dict], user: dict | None) -> list[str]:
    """Searches whose control reaches the leakage ceiling cannot show a leak as "beyond": say so where
    the search's own pick reaches most of the user's key (seen on ACT action chunks, where unbounded
    moves of the whole chunk clip leakage at 1 on the original too)."""
    if user is None:
        return []
    out = []
    for g in groups:
        c = g["control"]
        if g["kind"] != "search" or not c or not c.get("available") or c["leakage"] is None:
            continue
        pick = (g.get("search") or {}).get("best_leakage")
        if c["leakage"]["worst"] >= SATURATED and pick is not None and pick >= 0.5 * user["leakage"] > 0:
            out.append(
                f"{g['name']}: its control reaches the leakage ceiling ({c['leakage']['worst']:.2f}), so "
                f"this row cannot show a leak beyond the original; the search's own pick reaches "
                f"{pick:.2f} (your key: {user['leakage']:.2f})"
            )
    return out


def _scan_speed(groups: list[dict]) -> dict | None:
    """The black-box scan's own throughput (keys x screening samples per second of scanning)."""
    for g in groups:
        if g["probe"] == "blackbox" and g.get("search"):
            s = g["search"]
            fields = (
                "scanned",
                "screen_samples",
                "path",
                "seconds",
                "keys_per_second",
                "evaluations_per_second",
                "evaluations_per_cpu_second",
            )
            return {f: s[f] for f in fields}
    return None


def _user(ctx: ProbeContext, key: np.ndarray) -> dict:
    v = ctx.probe_keys(key, "user", outputs=True)
    return {
        "personalization": metrics.personalization(v["outputs"][0], ctx.ref.p, ctx.ref.b, ctx.ref.task),
        "leakage": float(v["leakage"][0]),
        "fidelity": float(v["fidelity"][0]),
    }


def _controls(probe, ctx, control_km, control_from, name, task, found) -> dict | None:
    """{group name: control JSON} for a probe with a control slot (key None: every other group);
    None for a probe without one."""
    if probe.control is None:
        return None
    if control_km is None:
        return {None: {"available": False, "reason": control_from}}
    found = probe.control(replace(ctx, probe=name), found)
    return {g.name: {"available": True, "model": control_from, **_group_json(g, task)} for g in found}


def leak_failures(report: dict, threshold: float) -> list[tuple[str, float]]:
    """(group, gated leakage) for every probe group above ``threshold``."""
    return [
        (g["name"], g["gate"]["value"])
        for g in report["groups"]
        if g["gate"] is not None and g["gate"]["value"] > threshold
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
