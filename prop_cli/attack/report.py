"""Presenting an audit report (schema ``prop-audit/2``): the table, the plot, the manifest summary."""

from __future__ import annotations

import time
from pathlib import Path

from prop_cli import constants as C
from prop_cli.bundle import update_manifest
from prop_cli.errors import PropError
from prop_cli.files import write_file

# Line styles of the reference lines, so overlapping searches stay distinguishable.
_STYLES = {"relaxed": "--", "relaxed-rounded": (0, (2, 3)), "latent": "-."}


def _ci(s: dict, fmt: str = ".4f") -> str:
    # summarize's interval is symmetric (normal approximation): mean ± half width is exact.
    return f"{s['mean']:{fmt}} ± {(s['ci95'][1] - s['ci95'][0]) / 2:{fmt}}"


def fidelity_label(task: str) -> str:
    return "fidelity (agreement)" if task == "classification" else "fidelity (mse to ref.)"


def title(report: dict) -> str:
    b, u = report["bundle"], report["user"]
    head = f"audit of {b['path']} ({b['task']}, {b['key_bits']}-bit {b['key_encoding']} keys)"
    samples = f"{report['data']['samples']} samples of {report['data']['path']}"
    if u is None:
        return f"{head}\nno key: reachable divergence only; {samples}"
    what = "1 - mse/mse_ref" if b["task"] == "regression" else "accuracy"
    return (
        f"{head}\nuser key: personalization {u['personalization']:.4f} ({what}), "
        f"leakage {u['leakage']:.4f}; {samples}"
    )


def _probe_name(g: dict) -> str:
    return g["name"] if g["threat"] == "cross-user" else f"{g['threat']} {g['name']}"


def _control_cell(g: dict, key: str, fmt: str) -> str:
    c = g.get("control")
    if c is None:
        return ""
    if not c.get("available"):
        return "n/a"
    return f"{c[key]['worst']:{fmt}}"


def table(report: dict):
    """A rich Table: one row per probe group."""
    from rich import box
    from rich.table import Table

    task = report["bundle"]["task"]
    owner = report["user"] is not None
    ffmt = ".3g" if task == "regression" else ".4f"
    t = Table(title=title(report), title_justify="left", box=box.SIMPLE_HEAD, pad_edge=False)
    t.add_column("probe", no_wrap=True)
    t.add_column("keys", justify="right", no_wrap=True)
    if owner:
        cols = ["leakage ± 95% CI", "worst", "pick", "control", "beyond", "fidelity"]
    else:
        cols = ["fidelity ± 95% CI", "worst", "pick", "control"]
    for c in cols:
        t.add_column(c, justify="right", no_wrap=True)
    for g in report["groups"]:
        srch = g.get("search")
        if owner:
            lk = g["leakage"]
            pick = f"{srch['best_leakage']:.4f}" if srch else ""
            beyond = "" if g["beyond"] is None else f"{g['beyond']:.4f}"
            row = [_ci(lk), f"{lk['worst']:.4f}", pick, _control_cell(g, "leakage", ".4f"), beyond,
                   f"{g['fidelity']['mean']:{ffmt}}"]  # fmt: skip
        else:
            fd = g["fidelity"]
            pick = f"{srch['best_fidelity']:{ffmt}}" if srch else ""
            row = [_ci(fd, ffmt), f"{fd['worst']:{ffmt}}", pick, _control_cell(g, "fidelity", ffmt)]
        t.add_row(_probe_name(g), str(g["keys"]), *row)
    notes = [
        f"fidelity: {'agreement' if task == 'classification' else 'mse'} with the reference output, "
        "mean over keys; worst: the group's worst key",
        "pick: the search restart with the largest divergence (the attacker's choice)",
        "control: the same probe's worst key where the bundle gives nothing (n/a: no original checkpoint, "
        "pass --original); beyond: worst - control, what --max-leak gates searches on when a control exists",
    ]
    if report.get("control_model"):
        notes.append(f"control model: {report['control_model']}")
    if any(g["name"] == "relaxed-rounded" and not g["is_key"] for g in report["groups"]):
        notes.append("T1 relaxed-rounded probes encoder codes; with hashed keys no known key maps to them")
    row = report.get("passphrase")
    if row:
        notes.append(
            f"passphrase: {row['guesses']:.3g} guesses (zxcvbn) x {row['seconds_per_guess'] * 1e3:.0f} ms "
            f"per scrypt guess = {row['core_years']:.3g} core-years to open: "
            + ("passed" if row["passed"] else f"FAILED (needs >= {row['min_core_years']:g})")
        )
    verdict = report.get("max_leak")
    if verdict:
        notes.append(
            f"--max-leak {verdict['threshold']}: "
            + ("passed" if verdict["passed"] else "FAILED (" + ", ".join(verdict["failing"]) + ")")
        )
    t.caption = "\n".join(notes)
    t.caption_justify = "left"
    return t


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
                "control_worst_leakage": _control_worst(g),
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
    row = report.get("passphrase")
    return {
        **_head(report),
        "figures": "sealed bundle: per-user figures are not recorded in the clear",
        "settings": {k: v for k, v in report["settings"].items() if k != "samples"},
        "groups": [{f: g[f] for f in ("name", "probe", "threat", "kind", "keys")} for g in report["groups"]],
        "max_leak": gate,
        "passphrase": None if row is None else {k: row[k] for k in ("passed", "min_core_years")},
    }


def _control_worst(g: dict) -> float | None:
    c = g.get("control")
    if not c or not c.get("available") or c.get("leakage") is None:
        return None
    return c["leakage"]["worst"]


def record(bundle_path: Path, report: dict) -> dict:
    """Write the summary into the bundle's manifest under ``audit`` (weights and their hashes untouched)."""
    s = summary(report)
    update_manifest(Path(bundle_path), C.M_AUDIT, s)
    return s


def plot(report: dict, path: Path) -> Path:
    """PNG: leakage and fidelity against Hamming distance, other probe groups as reference lines."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise PropError(
            "--plot needs matplotlib, which is not installed", "pip install prop-cli[plot]"
        ) from None

    task = report["bundle"]["task"]
    owner = report["user"] is not None
    groups = report["groups"]
    ham = [g for g in groups if g["distance"] is not None]
    refs = [g for g in groups if g["distance"] is None]
    metrics_ = [("leakage", "leakage (0 = nothing leaks)")] if owner else []
    metrics_.append(("fidelity", fidelity_label(task)))
    fig, axes = plt.subplots(1, len(metrics_), figsize=(6.4 * len(metrics_), 6.0), squeeze=False)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, (m, label) in zip(axes[0], metrics_):
        if ham:
            d = [g["distance"] for g in ham]
            mean = [g[m]["mean"] for g in ham]
            err = [
                [g[m]["mean"] - g[m]["ci95"][0] for g in ham],
                [g[m]["ci95"][1] - g[m]["mean"] for g in ham],
            ]
            ax.errorbar(
                d, mean, yerr=err, fmt="o-", color="black", capsize=3, label="Hamming d: mean, 95% CI"
            )
            ax.plot(d, [g[m]["worst"] for g in ham], "x--", color="grey", label="Hamming d: worst key")
            ax.set_xticks(d)
            ax.set_xlabel("Hamming distance from the user's key (bits)")
        else:
            ax.set_xticks([])
        for i, g in enumerate(refs):
            value = g["search"][f"best_{m}"] if g.get("search") else g[m]["mean"]
            what = "search pick" if g.get("search") else ("mean" if g["keys"] > 1 else "")
            colour = colours[i % len(colours)]
            style = _STYLES.get(g["name"], "-" if g["threat"] == "T0" else (0, (1, 1)))
            name = f"{g['threat']} {g['name']}" if g["threat"] != "cross-user" else g["name"]
            label_ = f"{name} {what}".strip() + f": {value:.3g}"
            if m == "leakage" and g.get("beyond") is not None:  # worst - control, what the gate may use
                label_ += f" (beyond control {g['beyond']:.3g})"
            ax.axhline(value, color=colour, linestyle=style, linewidth=1.6, label=label_)
            c = g.get("control")
            if c and c.get("available"):
                cv = c["search"][f"best_{m}"] if c.get("search") else c[m]["mean"]
                ax.axhline(cv, color=colour, linestyle=":", linewidth=1.0, alpha=0.7,
                           label=f"{name} control (original): {cv:.3g}")  # fmt: skip
            if g["name"] == "random":
                w = g[m]["worst"]
                ax.axhline(
                    w, color=colour, linestyle=":", linewidth=1.2, label=f"T0 random worst key: {w:.3g}"
                )
        if owner and m == "leakage":
            ax.set_ylim(-0.03, 1.03)
        elif task == "regression":
            ax.set_yscale("symlog", linthresh=1e-4)
            ax.set_ylim(0, max([*ax.get_ylim(), 1e-3]) * 3)  # headroom: top lines stay visible
        else:
            ax.set_ylim(-0.03, 1.03)
        ax.set_ylabel(label)
        ax.set_title(label)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2, frameon=False)
    fig.suptitle(title(report), fontsize=9)
    fig.tight_layout()
    try:
        return write_file(
            Path(path), lambda tmp: fig.savefig(tmp, dpi=110, format="png"), "--plot file", "--plot"
        )
    finally:
        plt.close(fig)
