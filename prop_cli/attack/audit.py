"""`prop attack`: how much of a user's personalization someone holding the bundle, not the key, reaches.

This module runs the registered probes (``probes``) and their controls on what ``target`` chooses,
and assembles the report (schema ``prop-audit/3``, documented in docs/audit.md); ``verdict`` gates
each row on what lies beyond its control and words the decision. Threat model:
docs/threat-model.md; metrics: docs/metrics.md. Probes score against the owner's targets only after
the fact; searches optimise on the inputs alone.
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
from prop_cli.errors import PropError
from prop_cli.files import sha256_file
from prop_cli.fit import prepare

from . import probes, target, verdict
from .probes.base import Counter, Group, ProbeContext, Progress, Reference
from .verdict import apply_max_leak, leak_failures

__all__ = ["apply_max_leak", "audit", "leak_failures"]

DEFAULT_HAMMING = "1..8"
# Below this leakage of the user's own key, its personalization is at the base's level (fix for a
# wrong key file, or data the bundle was not personalized on, going unnoticed).
WRONG_KEY_LEAKAGE = 0.5
# Per-candidate lists in a search's JSON only up to this many candidates (a key scan keeps hundreds).
PER_RESTART_LISTS = 256
MAX_SHOTS = 64  # the largest few-shot k
UNENROLLED = "no user enrolled: {} keyed with a fresh, untrained encoder (every key runs it)"


def sample_index(data: Dataset, n: int, seed: int) -> np.ndarray:
    order = np.random.default_rng(seed).permutation(len(data))
    return np.sort(order[: min(n, len(data))])


@torch.inference_mode()
def outputs(module: torch.nn.Module, x: torch.Tensor, rows: int | None) -> torch.Tensor:
    """``module(x)``, ``rows`` rows per forward (None: all at once)."""
    step = rows or len(x)
    return torch.cat([module(x[i : i + step]) for i in range(0, len(x), step)])


def shot_rows(
    data: Dataset, audit_rows: np.ndarray, seed: int, dev, reference, task: str
) -> Reference | None:
    """Up to MAX_SHOTS labelled rows outside the audit sample: what a few-shot attacker holds."""
    rest = np.setdiff1d(np.arange(len(data)), audit_rows)
    if not len(rest):
        return None
    rows = np.random.default_rng([seed, 1]).permutation(rest)[:MAX_SHOTS]
    x = torch.from_numpy(data.x[rows]).to(dev)
    p = torch.from_numpy(data.y[rows]).to(dev)
    if task == "regression" and p.dim() == 1:
        p = p[:, None]
    b = outputs(reference, x, target.rows_per_forward(reference))
    return Reference(x, b.clone(), p, task)


def _control_model(
    bundle: Bundle, km: KeyedModel, original: torch.nn.Module | None
) -> tuple[KeyedModel | None, str]:
    """The searches' control model: the original checkpoint keyed at the bundle's layers (the bundle's
    encoder shape, never its weights: the searches use only its layers and range), or why there is none."""
    if original is not None and target.is_the_base(bundle, km, original):
        original, where = km.module, "the original checkpoint (--original), equal to the sealed base"
    elif original is not None:
        where = "the original checkpoint (--original)"
    else:
        original, where = target.default_original(bundle, km)
        if original is None:
            return None, where
    mods = dict(original.named_modules())
    base = dict(km.module.named_modules())
    if not all(n in mods and mods[n].weight.shape == base[n].weight.shape for n in km.layer_names):
        return None, "the original module does not have the bundle's keyed layers (names and shapes)"
    return target.unenrolled_model(km, original, 0), where


def _measure(kind: str) -> str:
    """The leakage a row is scored on: leakage for concrete keys, bounded leakage for searches."""
    return "bounded" if kind == "search" else "leakage"


def _summary(v: dict[str, torch.Tensor], task: str, kind: str) -> dict:
    worst_fid = "min" if task == "classification" else "max"
    out = {
        "keys": int(len(v["fidelity"])),
        "leakage": metrics.summarize(v[_measure(kind)], "max") if "leakage" in v else None,
        "fidelity": metrics.summarize(v["fidelity"], worst_fid),
    }
    if kind == "search":  # the unbounded figure, for reference: a far move can reach 1 on any model
        out["leakage_unbounded"] = metrics.summarize(v["leakage"], "max") if "leakage" in v else None
    return out


def _search(v: dict[str, torch.Tensor], info: dict, kind: str) -> dict:
    best = int(torch.argmax(v["divergence"]))  # the attacker's pick: it cannot see the targets
    lk = v.get(_measure(kind))
    return {
        **info,
        "best_restart": best,
        "best_divergence": float(v["divergence"][best]),
        "best_leakage": float(lk[best]) if lk is not None else None,
        "best_fidelity": float(v["fidelity"][best]),
        **_per_restart(v, lk),
    }


def _per_restart(v: dict[str, torch.Tensor], lk: torch.Tensor | None) -> dict:
    if len(v["divergence"]) > PER_RESTART_LISTS:
        return {}
    return {
        "divergence": [float(d) for d in v["divergence"]],
        "leakage": [float(d) for d in lk] if lk is not None else None,
    }


def _group_json(g: Group, task: str, kind: str) -> dict:
    out = {"name": g.name, "distance": g.distance, "is_key": g.is_key, **_summary(g.values, task, kind)}
    if g.search is not None:
        out["search"] = _search(g.values, g.search, kind)
    return out


def _row(g: Group, probe: probes.Probe, task: str) -> dict:
    kind = g.kind or probe.kind
    threat = g.threat or probe.threat
    row = {"probe": probe.name, "threat": threat, "kind": kind, **_group_json(g, task, kind)}
    return {**row, **(g.extra or {}), "control": None, "beyond": None, "gate": None}


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


def _with_original(chosen: list[str], known: bool, asked: bool) -> list[str]:
    """``chosen`` without the probes that need the original where it is not known (named in --probes:
    an error saying how to give it)."""
    needing = [p for p in chosen if probes.probe_named(p).needs == "original"]
    if known or not needing:
        return chosen
    if asked:
        raise PropError(
            f"--probes {','.join(needing)} need the original checkpoint (the bundle's base was trained "
            "with the key)",
            "pass --original with the checkpoint the bundle was personalized from, or leave those probes out",
        )
    return [p for p in chosen if p not in needing]


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
    """Run the audit; returns the report (schema ``prop-audit/3``, documented in docs/audit.md).

    ``keys[0]`` is the audited user's key (their targets are ``data.y``), ``keys[1:]`` other keys (a
    cross-user row each if they are users of the bundle, else a plain key row); no keys = a no-key
    audit. ``original`` is the original checkpoint's module: the reference b (default: the bundle
    without a key) and the model the searches' controls run on; the key rows' control is the reference
    keyed with a fresh encoder. A policy bundle is audited as an array model: pass it and its data
    through ``target.as_array`` first. ``verdict.apply_max_leak`` adds the --max-leak decision.
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
    with target.memo(km.module):  # what a policy computes once for every key (SmolVLA: images)
        idx = sample_index(data, s.samples, s.seed)
        x = torch.from_numpy(data.x[idx]).to(dev)
        b = outputs(original.to(dev).eval() if original is not None else km.module, x, km.max_rows)
        p = None
        if has_key:
            p = torch.from_numpy(data.y[idx]).to(dev)
            if task == "regression" and p.dim() == 1:
                p = p[:, None]
        shots = (
            shot_rows(data, idx, s.seed, x.device, km.module if original is None else original, task)
            if has_key
            else None
        )
        control_km, control_from = _control_model(bundle, km, original)
        s.probes = _with_original(s.probes, control_km is not None, settings.probes is not None)
        reference = original if original is not None else km.module  # what gives b
        unenrolled = target.unenrolled_model(km, reference, s.seed)
        models = {
            "key": UNENROLLED.format("the original checkpoint" if original is not None else
                                     "the reference (the bundle's base, no key)"),
            "search": control_from,
        }  # fmt: skip
        ref = Reference(x, b.clone(), p, task)  # clone: out of inference mode, usable next to autograd
        counter = Counter()
        seed = bundle.manifest.get(C.M_CONFIG, {}).get("seed")
        deadline = started + s.budget if s.budget is not None else None
        ctx = ProbeContext(km, ref, s, list(keys), bundle.key_encoding, control_km, unenrolled, progress,
                           counter, shots=shots, seed_hint=seed if isinstance(seed, int) else None,
                           users=bundle.mode.users(bundle.manifest), deadline=deadline)  # fmt: skip
        ctx = target.probe_context(bundle, ctx)
        # Every model here without a key gives b (the same weights on the same samples): kept, not rerun.
        for k in (unenrolled, control_km, km if original is None else None):
            if k is not None:
                ctx.kept[id(k.module)] = (k.module, x, ref.b)
        timing: dict[str, float] = {}
        groups: list[dict] = []
        user, warnings, not_tried = None, [], []
        try:
            if has_key:
                user = _user(ctx, keys[0])
                warnings += _enrolment(bundle, keys[0])
                if user["leakage"] < WRONG_KEY_LEAKAGE:
                    warnings.append(
                        f"the key shows little of the personalization (leakage of your own key "
                        f"{user['leakage']:.2f}, personalization {user['personalization']:.2f}): it may not "
                        f"be this bundle's key, or --data not the data it was personalized on"
                    )
            chosen = [n for n in s.probes if probes.probe_named(n).needs != "other-keys" or len(keys) > 1]
            for i, name in enumerate(chosen):
                probe = probes.probe_named(name)
                here = replace(ctx, probe=name)
                cheap = target.cheap_when_late(bundle, probe) or (
                    probe.known is not None and probe.known(here)
                )
                if ctx.out_of_time() and not cheap:
                    not_tried.append(name)
                    continue
                t0 = time.perf_counter()
                # Each probe (with its control) gets an even share of what is left of the budget, so one
                # probe's many keys do not leave the others untried; what it leaves goes to the next.
                share = None if deadline is None or cheap else t0 + (deadline - t0) / (len(chosen) - i)
                here = replace(ctx, probe=name, deadline=share)
                found = probe.run(here)
                rows = [_row(g, probe, task) for g in found]
                _controls(probe, here, found, rows, models, task)
                said = [line for p, line in ctx.shortcuts if p == name]  # the work done once, not repeated
                for row in rows:
                    row["shortcuts"] = said
                timing[name] = time.perf_counter() - t0
                warnings += [g.note for g in found if g.note]
                groups += rows
        finally:
            for prm, flag in zip(km.parameters(), grad_flags):
                prm.requires_grad_(flag)
    warnings += ctx.notes
    saturable = target.controls_can_saturate(bundle)
    for row in groups:
        row["gate"] = verdict.gate(row, saturable)
    warnings += verdict.ceiling_warnings(groups)
    coverage = {"budget_seconds": s.budget, "not_tried": not_tried, "cut_short": list(ctx.cut)}

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
            "users": ctx.users,
            "keyed_layers": bundle.manifest[C.M_KEYED_LAYERS],
        },
        "data": {"path": str(data.path), "rows": len(data), "samples": int(len(idx))},
        "reference": "original" if original is not None else "bundle-no-key",
        "control_model": control_from if control_km is not None else None,
        "key_control_model": models["key"],
        "key_rows": target.key_rows(bundle),
        "remedy": target.remedy(bundle),
        "settings": {**asdict(s), "other_users": max(0, len(keys) - 1), "device": str(dev)},
        "user": user,
        "warnings": warnings,
        "coverage": coverage,
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
        return [
            f"{bundle.mode.not_enrolled(str(bundle.path))}: prop run refuses this key "
            "(--allow-unenrolled-key runs the bundle's base for it)"
        ]
    except PropError as e:
        return [e.what]


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


def _controls(
    probe, ctx: ProbeContext, found: list[Group], rows: list[dict], models: dict, task: str
) -> None:
    """Attach each row's control: the control group of the same name, or why there is none (a row of a
    probe without a control slot keeps None)."""
    if probe.control is None:
        return
    got = {g.name: g for g in probe.control(ctx, found)}
    for g, row in zip(found, rows):
        c = got.get(g.name)
        if c is None:
            why = row.pop("control_unavailable", None) or models["search"]
            row["control"] = {"available": False, "reason": why}
        else:
            row.pop("control_unavailable", None)
            row["control"] = {"available": True, "model": c.model or models[row["kind"]],
                              **_group_json(c, task, row["kind"])}  # fmt: skip
