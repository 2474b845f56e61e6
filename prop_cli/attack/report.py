"""What of an audit report (schema ``prop-audit/3``) a bundle keeps: the manifest summary (``record``) and
what `prop inspect` reads back from it. Showing a report (decision lines, table, plot) is
``prop_cli.present``'s."""

from __future__ import annotations

import time
from pathlib import Path

from prop_cli import constants as C
from prop_cli.bundle import update_manifest


def control_worst(g: dict, key: str = "leakage") -> float | None:
    c = g.get("control")
    if not c or not c.get("available") or c.get(key) is None:
        return None
    return c[key]["worst"]


def summary(report: dict) -> dict:
    """The compact audit record stored in the bundle manifest (never the key). A sealed bundle's manifest
    is public while its users' figures are sealed: its record keeps verdicts and settings only, no
    leakage, fidelity, personalization or sample count (``sealed_summary``)."""
    if report["bundle"].get("sealed"):
        return sealed_summary(report)
    return {
        **_head(report),
        "reference": report["reference"],
        "samples": report["data"]["samples"],
        "settings": report["settings"],
        "user": report["user"],
        "groups": [
            {
                "name": g["name"],
                "probe": g["probe"],
                "threat": g["threat"],
                "kind": g["kind"],
                "keys": g["keys"],
                "leakage": g["leakage"],
                "fidelity_mean": g["fidelity"]["mean"],
                "search_pick_leakage": (g.get("search") or {}).get("best_leakage"),
                "control_worst_leakage": control_worst(g),
                "beyond": g["beyond"],
                "gate": g["gate"],
            }
            for g in report["groups"]
        ],
        "max_leak": report.get("max_leak"),
    }


def _head(report: dict) -> dict:
    """What every recorded summary starts with: schema, when, by which prop, of which manifest."""
    return {
        "schema": report["schema"],
        "recorded_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "prop_version": report["prop_version"],
        "mode": report["mode"],
        "audited_manifest_sha256": report["bundle"]["manifest_sha256"],
    }


def sealed_summary(report: dict) -> dict:
    """What of an audit a sealed bundle's clear manifest may say: which probes ran and the verdicts."""
    gate = report.get("max_leak")
    if gate:  # the verdict, not the figures behind it (its headline and reason quote them)
        gate = {k: gate[k] for k in ("threshold", "passed", "failing")}
    row = report.get("passphrase")
    return {
        **_head(report),
        "figures": "sealed bundle: per-user figures are not recorded in the clear",
        "settings": {k: v for k, v in report["settings"].items() if k != "samples"},
        "groups": [{f: g[f] for f in ("name", "probe", "threat", "kind", "keys")} for g in report["groups"]],
        "max_leak": gate,
        "passphrase": None if row is None else {k: row[k] for k in ("passed", "min_core_years")},
    }


def default_probes(mode: str | None) -> list[str]:
    """The probes a default audit runs: every default probe, without those that need the user's key in
    a no-key audit (``audit._settings`` chooses the same), and without those that run only where the
    original is known (``--original``: an audit without it runs every other default probe)."""
    from . import probes

    chosen = [p for p in probes.select(None) if probes.probe_named(p).needs != "original"]
    if mode == "no-key":
        chosen = [p for p in chosen if probes.probe_named(p).needs != "key"]
    return chosen


def recorded_coverage(audit: dict) -> dict:
    """Of a recorded audit as `prop inspect` reads it (``bundle.describe``): the default probes it did
    not run (``missing_probes``; None where the record does not name its probes) and whether its
    --max-leak decision may be shown as a pass (``passed``: it passed and ran every default probe)."""
    ran = audit.get("probes")
    missing = None if ran is None else [p for p in default_probes(audit.get("mode")) if p not in ran]
    leak = audit.get("max_leak")
    passed = bool(leak and leak.get("passed") and missing == [])
    return {"missing_probes": missing, "passed": passed}


def record(bundle_path: Path, report: dict) -> dict:
    """Write the summary into the bundle's manifest under ``audit`` (weights and their hashes untouched)."""
    s = summary(report)
    update_manifest(Path(bundle_path), C.M_AUDIT, s)
    return s
