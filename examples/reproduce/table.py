"""The Fig.-4-style table: columns random key / Hamming-1 neighbour / user key, rows general and
personalized objective (plus leakage), one block per method, mean +- standard error over seeds.

Significance: for every cell of a PRoP block, Welch's t-test (scipy) of PRoP's per-seed values against
those of the best of the paper's baselines (MLP, CVAE: raw key bits) in that cell ("best" in the cell's
desired direction); ``*`` marks PRoP significantly better (p < 0.05), ``!`` significantly worse. Other
baseline blocks (MLP-hashed: the MLP fed prop's hashed key code) are ablations, compared separately.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

COLUMNS = ("random", "hamming1", "user", "t2")
COLUMN_TITLES = {"random": "random key", "hamming1": "Hamming-1", "user": "user key", "t2": "T2 latent"}
ROWS = ("general", "personal", "leakage")
ALPHA = 0.05
PAPER_BASELINES = ("MLP", "CVAE")
ORDER = ("PRoP", "PRoP-hashed", "MLP", "MLP-hashed", "CVAE")


def ordered(methods: dict) -> list[str]:
    """Methods in the table's order (PRoP blocks first), whatever order a JSON file kept."""
    return sorted(methods, key=lambda m: ORDER.index(m) if m in ORDER else len(ORDER))


def is_prop(method: str) -> bool:
    return method.startswith("PRoP")


def desired(row: str, col: str, higher_is_better: bool) -> str:
    """'high' or 'low': what an ideal method shows in this cell (the paper's arrows)."""
    if row == "leakage":
        return "high" if col == "user" else "low"
    wants_good = (row == "general") != (col == "user")  # general off-key, personal on-key
    return "high" if wants_good == higher_is_better else "low"


def mean_se(values: list[float]) -> tuple[float, float]:
    v = np.asarray(values, dtype=np.float64)
    se = float(v.std(ddof=1) / math.sqrt(len(v))) if len(v) > 1 else float("nan")
    return float(v.mean()), se


def welch_p(a: list[float], b: list[float]) -> float:
    """Two-sided Welch's t-test; exact answers where a sample has no spread (t-test undefined)."""
    a_, b_ = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if len(a_) < 2 or len(b_) < 2:
        return float("nan")
    if a_.std() == 0 and b_.std() == 0:
        return 1.0 if a_.mean() == b_.mean() else 0.0
    import warnings

    from scipy.stats import ttest_ind

    with warnings.catch_warnings():  # near-identical samples: scipy warns, the p-value is still usable
        warnings.simplefilter("ignore", RuntimeWarning)
        return float(ttest_ind(a_, b_, equal_var=False).pvalue)


def significance(result: dict) -> dict:
    """{method: {row: {col: (mark, p, best_baseline)}}} for the PRoP blocks."""
    hib = result["higher_is_better"]
    methods = result["methods"]
    base = [m for m in methods if m in PAPER_BASELINES] or [m for m in methods if not is_prop(m)]
    out: dict = {}
    for m, cells in methods.items():
        if not is_prop(m) or not base:
            continue
        out[m] = {}
        for row, cols in cells.items():
            for col, vals in cols.items():
                cands = [(b, methods[b].get(row, {}).get(col)) for b in base]
                cands = [(b, v) for b, v in cands if v]
                if not vals or not cands:
                    continue
                up = desired(row, col, hib) == "high"
                best, bv = max(cands, key=lambda c: np.mean(c[1]) if up else -np.mean(c[1]))
                p = welch_p(vals, bv)
                better = (np.mean(vals) > np.mean(bv)) == up
                mark = ("*" if better else "!") if p < ALPHA else ""
                out[m].setdefault(row, {})[col] = (mark, p, best)
    return out


def _fmt(values: list[float] | None, digits: int) -> str:
    if not values:
        return "—"
    m, se = mean_se(values)
    if math.isnan(se):
        return f"{m:.{digits}f}"
    return f"{m:.{digits}f} ± {se:.{digits}f}"


def markdown(result: dict, digits: int = 3) -> str:
    """The table as GitHub markdown (also readable as plain text)."""
    sig = significance(result)
    labels = result["row_labels"]
    cols = [c for c in COLUMNS if any(c in r for m in result["methods"].values() for r in m.values())]
    arrows = "↑" if result["higher_is_better"] else "↓"
    lines = [
        f"**{result['title']}** — {result['seeds']} seeds, mean ± s.e.; objective {result['objective']} "
        f"({arrows} = better at the behaviour asked for)",
        "",
        "| method | row | " + " | ".join(COLUMN_TITLES[c] for c in cols) + " |",
        "|---|---|" + "---|" * len(cols),
    ]
    hib = result["higher_is_better"]
    for m in ordered(result["methods"]):
        cells = result["methods"][m]
        for row in ROWS:
            if row not in cells:
                continue
            parts = []
            for c in cols:
                vals = cells[row].get(c)
                mark = sig.get(m, {}).get(row, {}).get(c, ("", 0, ""))[0]
                want = "↑" if desired(row, c, hib) == "high" else "↓"
                parts.append(f"{_fmt(vals, digits)}{mark} {want}" if vals else "—")
            lines.append(f"| {m} | {labels[row]} | " + " | ".join(parts) + " |")
    lines += [
        "",
        "Arrow in a cell: the direction an ideal method takes there. `*` / `!`: PRoP significantly "
        f"better / worse than the best of the paper's baselines (MLP, CVAE) in that cell (Welch's t-test "
        f"over seeds, p < {ALPHA}).",
    ]
    lines += ablation_lines(result)
    if result.get("notes"):
        lines += [""] + [f"- {n}" for n in result["notes"]]
    return "\n".join(lines)


def ablation_lines(result: dict) -> list[str]:
    """PRoP-hashed against MLP-hashed (same key encoding): which cells differ significantly."""
    methods = result["methods"]
    a, b = "PRoP-hashed", "MLP-hashed"
    if a not in methods or b not in methods:
        return []
    better, worse = [], []
    for row, cols in methods[a].items():
        for col, vals in cols.items():
            other = methods[b].get(row, {}).get(col)
            if not other or welch_p(vals, other) >= ALPHA:
                continue
            up = desired(row, col, result["higher_is_better"]) == "high"
            name = f"{row}/{COLUMN_TITLES[col]}"
            (better if (np.mean(vals) > np.mean(other)) == up else worse).append(name)
    return [
        "",
        f"Same key encoding ({a} vs {b}, Welch p < {ALPHA}): {a} better in "
        f"{', '.join(better) or 'no cell'}; worse in {', '.join(worse) or 'no cell'}.",
    ]


def plot(result: dict, path: Path) -> Path | None:
    """Bars per method with standard-error whiskers; one panel per (row, column). None without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    sig = significance(result)
    rows = [r for r in ("general", "personal") if any(r in m for m in result["methods"].values())]
    cols = ("random", "hamming1", "user")
    methods = ordered(result["methods"])
    fig, axes = plt.subplots(len(rows), len(cols), figsize=(3.2 * len(cols), 2.6 * len(rows)), squeeze=False)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, row in enumerate(rows):
        for j, col in enumerate(cols):
            ax = axes[i][j]
            for k, m in enumerate(methods):
                vals = result["methods"][m].get(row, {}).get(col)
                if not vals:
                    continue
                mu, se = mean_se(vals)
                ax.bar(k, mu, yerr=0 if math.isnan(se) else se, color=colours[k % len(colours)], capsize=3)
                mark = sig.get(m, {}).get(row, {}).get(col, ("",))[0]
                if mark:  # above the whisker, so "!" is not read as an error bar
                    top = mu + (0 if math.isnan(se) else se)
                    ax.text(k, top, mark, ha="center", va="bottom", fontsize=11, color="black", weight="bold")
            want = "↑" if desired(row, col, result["higher_is_better"]) == "high" else "↓"
            ax.set_title(f"{COLUMN_TITLES[col]} {want}", fontsize=9)
            ax.set_xticks(range(len(methods)), methods, fontsize=7, rotation=20)
            if j == 0:
                ax.set_ylabel(result["row_labels"][row], fontsize=8)
    fig.suptitle(result["title"], fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
