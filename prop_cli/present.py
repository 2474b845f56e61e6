"""Showing results to a person: an audit report (schema ``prop-audit/3``) as decision lines, a table and a
plot. The table and the plot draw the same numbers (``cells``). Nothing here computes a result: the
report is ``prop_cli.attack``'s; the CLI prints what this returns."""

from __future__ import annotations

from pathlib import Path

from prop_cli.attack import verdict
from prop_cli.attack.report import control_worst
from prop_cli.errors import PropError
from prop_cli.files import write_file


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
    return g["name"] if g["threat"] in ("cross-user", g["name"]) else f"{g['threat']} {g['name']}"


def cells(report: dict) -> list[dict]:
    """Per row, the numbers the table prints and the plot draws, and their text: ``label``, ``keys``,
    ``mean``/``half`` (95% interval), ``worst``, ``pick``, ``control``, ``beyond``, ``fidelity``,
    ``gated`` (what --max-leak compares) and ``on`` (beyond-control, or the row's own figure: "no
    control" / "ceiling"). With a key the figures are leakage, without one fidelity."""
    owner = report["user"] is not None
    task = report["bundle"]["task"]
    m = "leakage" if owner else "fidelity"
    fmt = ".4f" if owner or task == "classification" else ".3g"
    out = []
    for g in report["groups"]:
        s, gate = g[m], g.get("gate")
        srch = g.get("search") or {}
        pick = srch.get(f"best_{m}") if "best_restart" in srch else None
        c = g.get("control")
        ctl = control_worst(g, m)
        on = "" if gate is None else ("beyond" if gate["on"] == "beyond-control" else gate["why"])
        row = {
            "label": _probe_name(g), "keys": g["keys"], "mean": s["mean"],
            "half": (s["ci95"][1] - s["ci95"][0]) / 2,
            "worst": s["worst"], "pick": pick, "control": ctl, "beyond": g.get("beyond") if owner else None,
            "fidelity": g["fidelity"]["mean"], "gated": gate["value"] if gate else None, "on": on,
        }  # fmt: skip
        row["text"] = {
            "keys": str(g["keys"]),
            "ci": f"{row['mean']:{fmt}} ± {row['half']:{fmt}}",
            "worst": f"{row['worst']:{fmt}}",
            "pick": "" if pick is None else f"{pick:{fmt}}",
            "control": "" if c is None else ("n/a" if ctl is None else f"{ctl:{fmt}}"),
            "beyond": "" if row["beyond"] is None else f"{row['beyond']:{fmt}}",
            "fidelity": f"{row['fidelity']:{'.3g' if task == 'regression' else '.4f'}}",
            "gated": "" if gate is None else f"{gate['value']:.4f}" + ("" if on == "beyond" else f" ({on})"),
        }
        out.append(row)
    return out


def coverage_line(cov: dict) -> str:
    """What the audit's time budget left out: the verdict covers the rest only."""
    parts = []
    if cov["cut_short"]:
        parts.append(f"cut short: {', '.join(cov['cut_short'])} (their rows hold what ran)")
    if cov["not_tried"]:
        parts.append(f"not tried: {', '.join(cov['not_tried'])}")
    return (f"coverage: the --budget of {cov['budget_seconds']:g} s ran out; " + "; ".join(parts)
            + " (a larger --budget, or fewer --samples, tries more)")  # fmt: skip


def decision(report: dict) -> list[str]:
    """The lines printed before the table: the decision (or, without --max-leak, the row that leaks most),
    then the failing rows by severity with what each means."""
    verdict_ = report.get("max_leak")
    head = verdict_["verdict"] if verdict_ else verdict.headline(report)
    cov = report.get("coverage") or {}
    lines = [coverage_line(cov)] if cov.get("not_tried") or cov.get("cut_short") else []
    if head is None:
        return lines
    lines.insert(0, head)
    if verdict_ and verdict_["rows"]:
        lines.append("failing rows, by severity (gated value: beyond the control, or the row's own figure):")
        width = max(len(r["name"]) for r in verdict_["rows"])
        for r in verdict_["rows"]:
            why = "" if r["on"] == "beyond-control" else f" ({r['why']})"
            lines.append(f"  {r['name']:{width}s}  {r['value']:.4f}{why}  {r['finding']}")
    return lines


def table(report: dict):
    """A rich Table: one row per probe group (the numbers of ``cells``)."""
    from rich import box
    from rich.table import Table

    task = report["bundle"]["task"]
    owner = report["user"] is not None
    t = Table(title=title(report), title_justify="left", box=box.SIMPLE_HEAD, pad_edge=False)
    t.add_column("probe", no_wrap=True)
    t.add_column("keys", justify="right", no_wrap=True)
    if owner:
        cols = ["leakage ± 95% CI", "worst", "pick", "control", "beyond", "gated", "fidelity"]
        keys = ["ci", "worst", "pick", "control", "beyond", "gated", "fidelity"]
    else:
        cols = ["fidelity ± 95% CI", "worst", "pick", "control"]
        keys = ["ci", "worst", "pick", "control"]
    for c in cols:
        t.add_column(c, justify="right", no_wrap=True)
    failing = set((report.get("max_leak") or {}).get("failing", []))
    for g, row in zip(report["groups"], cells(report)):
        texts = [row["text"][k] for k in keys]
        if g["name"] in failing:
            texts[keys.index("gated")] += " FAIL"
        t.add_row(row["label"], row["text"]["keys"], *texts)
    notes = [
        f"fidelity: {'agreement' if task == 'classification' else 'mse'} with the reference output, "
        "mean over keys; worst: the group's worst key",
        "leakage: key rows (concrete keys and codes) score leakage; search rows (T1 relaxed, T2, T3 fits) "
        "bounded leakage: a move larger than yours is scaled back to yours (docs/metrics.md)",
        "pick: the search restart with the largest divergence (the attacker's choice)",
        "control: the same probe's worst where the bundle gives nothing: key rows, the same keys with no "
        "user enrolled; searches, the same attack on the original (n/a: pass --original)",
        "beyond: worst - control; gated: what --max-leak compares (beyond, or the row's own figure when "
        "there is no control or a search's control is at the ceiling)",
    ]
    if report.get("key_rows"):
        notes.append(report["key_rows"])
    if report.get("control_model"):
        notes.append(f"search control model: {report['control_model']}")
    if any(not g["is_key"] and g["kind"] == "key" for g in report["groups"]):
        notes.append("rows of codes (structure, rounded searches) probe encoder codes; with hashed keys no "
                     "known key maps to them, but anyone with the files can run them")  # fmt: skip
    row = report.get("passphrase")
    if row:
        notes.append(
            f"passphrase: {row['guesses']:.3g} guesses (zxcvbn) x {row['seconds_per_guess'] * 1e3:.0f} ms "
            f"per scrypt guess = {row['core_years']:.3g} core-years to open: "
            + ("passed" if row["passed"] else f"FAILED (needs >= {row['min_core_years']:g})")
        )
    t.caption = "\n".join(notes)
    t.caption_justify = "left"
    return t


def check_plot() -> None:
    """Fail before any probe runs when --plot cannot be drawn (matplotlib is an extra)."""
    import importlib.util

    if importlib.util.find_spec("matplotlib") is None:
        raise PropError("--plot needs matplotlib, which is not installed", "pip install 'prop-keys[plot]'")


def plot(report: dict, path: Path) -> Path:
    """PNG of the table's numbers (``cells``): per row, the worst (bar), its control (black tick) and
    beyond, written beside it as in the table; the --max-leak threshold as a line; Hamming rows' mean
    and 95% interval as points. Without a key, fidelity instead of leakage."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise PropError(
            "--plot needs matplotlib, which is not installed", "pip install 'prop-keys[plot]'"
        ) from None

    fig = figure(report, plt)
    try:
        return write_file(
            Path(path), lambda tmp: fig.savefig(tmp, dpi=110, format="png"), "--plot file", "--plot"
        )
    finally:
        plt.close(fig)


def figure(report: dict, plt):
    """The plot's figure (``plot``), for tests to read back."""
    owner = report["user"] is not None
    rows = cells(report)
    metric = "leakage (0 = nothing leaks)" if owner else fidelity_label(report["bundle"]["task"])
    fig, ax = plt.subplots(figsize=(9.0, 1.2 + 0.32 * max(1, len(rows))))
    y = list(range(len(rows)))[::-1]
    failing = set((report.get("max_leak") or {}).get("failing", []))
    colours = ["tab:red" if g["name"] in failing else "tab:blue" for g in report["groups"]]
    ax.barh(y, [r["worst"] for r in rows], color=colours, alpha=0.6, label="worst")
    ax.errorbar([r["mean"] for r in rows], y, xerr=[r["half"] for r in rows], fmt="o", color="grey",
                markersize=3, capsize=2, label="mean, 95% CI")  # fmt: skip
    ctl = [(yy, r["control"]) for yy, r in zip(y, rows) if r["control"] is not None]
    if ctl:
        ax.scatter([c for _, c in ctl], [yy for yy, _ in ctl], marker="|", s=160, color="black",
                   label="control (worst)")  # fmt: skip
    for yy, r in zip(y, rows):
        parts = [r["text"]["worst"]]
        if r["text"]["control"]:
            parts.append(f"control {r['text']['control']}")
        if r["text"]["beyond"]:
            parts.append(f"beyond {r['text']['beyond']}")
        ax.text(1.02, yy, "  ".join(parts), va="center", fontsize=7, transform=ax.get_yaxis_transform())
    threshold = (report.get("max_leak") or {}).get("threshold")
    if threshold is not None:
        ax.axvline(threshold, color="tab:red", linestyle="--", linewidth=1, label=f"--max-leak {threshold:g}")
    ax.set_yticks(y)
    ax.set_yticklabels([r["label"] for r in rows], fontsize=7)
    if owner or report["bundle"]["task"] == "classification":
        ax.set_xlim(-0.02, 1.02)
    else:
        ax.set_xscale("symlog", linthresh=1e-4)
    ax.set_xlabel(metric)
    ax.grid(axis="x", alpha=0.3)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.08 - 2.0 / fig.get_figheight() / 10),
              ncol=4, frameon=False)  # fmt: skip
    fig.suptitle(title(report), fontsize=8)
    fig.tight_layout()
    return fig
