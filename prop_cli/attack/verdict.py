"""The audit's gate and verdict: what each row is judged on, and the decision `--max-leak` prints first.

Every row is gated on what lies beyond its control (docs/threat-model.md, "The gate"):

- key rows (concrete keys or codes: T0, structure, a search's rounding, other users' keys): their
  leakage beyond the same keys where no user was enrolled (the reference itself, so 0 for every key
  probe but the cross-user row of a sealed bundle, whose control is the other user's own record);
- search rows (what an optimiser reaches): their bounded leakage (``metrics.bounded_leakage``) beyond
  the same attack's on the original.

A row is gated on its own figure instead when its control is unavailable (no original checkpoint), or
when a search's control reaches the ceiling (``CEILING``): that control cannot show a leak beyond it,
so the row fails unless its own figure is within the threshold. The verdict names the failing rows by
severity: the largest gated value first, and among rows within ``TIE`` of it the attack that needs the
least (``ACCESS``): reading the files before running keys, before searching, before the user's samples.
"""

from __future__ import annotations

from prop_cli.errors import PropError

CEILING = 0.99  # a search control's worst leakage at or above this cannot separate the bundle
TIE = 0.01  # gated values this close count as equal when ranking rows
# What an attack needs, least first: the files alone, keys anyone can try, searches over the files, another
# user's key, the user's own labelled samples.
ACCESS = {"structure": 0, "T0": 1, "T1": 2, "T2": 3, "cross-user": 4, "T3": 5}
# What a failing row means, by probe (or by row name, for a search's rounding).
FINDINGS = {
    "null": "the bundle shows your behaviour without any key",
    "random": "random keys show part of your behaviour",
    "hamming": "keys a few bits from yours show part of your behaviour",
    "blackbox": "a scan of random keys finds keys that show your behaviour",
    "structure": "your code can be read off the encoder's weights",
    "drift": "the base's move from the original points at where your data lies",
    "relaxed": "a search through the encoder reaches your behaviour",
    "relaxed-rounded": "a search through the encoder finds a code that runs your behaviour",
    "latent": "optimising the keyed layers reaches your behaviour beyond what it reaches on the original",
    "fewshot": "a few of your labelled samples recover your behaviour through the bundle, beyond "
    "fine-tuning the original on them",
    "fewshot-rounded": "a code fitted to a few of your labelled samples runs your behaviour",
    "cross-user": "another user's key shows your behaviour beyond their own",
    "plain-key": "this key shows your behaviour",
    "your-key": "this key runs your own behaviour (it is your key, or opens your record)",
    "cross-user-shared": "another user's key shows your behaviour, and with users sharing one encoder the "
    "audit cannot tell how much of it is their own",
}
NOTHING_RAN = "no probe ran (the report's coverage says which were not tried): not a pass"
CEILING_FINDING = (
    "the same attack gets your behaviour from the original too (control at the ceiling), so the audit "
    "cannot tell what the bundle adds"
)


def finding(row: dict) -> str:
    """One line: what the row's leak means (the verdict's reason)."""
    if (row.get("gate") or {}).get("why") == "control at the ceiling":
        return CEILING_FINDING
    if row["probe"] == "cross-user" and row["threat"] == "T0":
        return FINDINGS["plain-key"]
    if (row.get("enrolment") or {}).get("yours"):
        return FINDINGS["your-key"]
    if row["probe"] == "cross-user" and (row.get("gate") or {}).get("why") == "no control":
        return FINDINGS["cross-user-shared"]
    if row["probe"] == "fewshot" and row["kind"] == "key":
        return FINDINGS["fewshot-rounded"]
    return FINDINGS.get(row["name"], FINDINGS.get(row["probe"], "it leaks"))


def gate(row: dict, saturable: bool) -> dict | None:
    """What --max-leak compares for this row (None without the user's targets); sets row["beyond"]."""
    lk = row["leakage"]
    if lk is None:
        return None
    c = row.get("control")
    if not (c and c.get("available") and c["leakage"] is not None):
        return {"on": "raw", "value": lk["worst"], "why": "no control"}
    row["beyond"] = max(0.0, lk["worst"] - c["leakage"]["worst"])
    if saturable and row["kind"] == "search" and c["leakage"]["worst"] >= CEILING:
        return {"on": "raw", "value": lk["worst"], "why": "control at the ceiling"}
    return {"on": "beyond-control", "value": row["beyond"], "why": None}


def ceiling_warnings(groups: list[dict]) -> list[str]:
    return [
        f"{g['name']}: its control reaches the leakage ceiling ({g['control']['leakage']['worst']:.2f}): "
        f"{CEILING_FINDING}; gated on its own figure ({g['gate']['value']:.2f})"
        for g in groups
        if (g.get("gate") or {}).get("why") == "control at the ceiling"
    ]


def severity(rows: list[dict]) -> list[dict]:
    """Rows by severity: the largest gated value first; rows within ``TIE`` of the largest left form one
    tier, ordered by the attack that needs least (then by value)."""
    left = sorted(rows, key=lambda g: -g["gate"]["value"])
    out: list[dict] = []
    while left:
        top = left[0]["gate"]["value"]
        tier = [g for g in left if g["gate"]["value"] >= top - TIE]
        out += sorted(tier, key=lambda g: (ACCESS.get(g["threat"], len(ACCESS)), -g["gate"]["value"]))
        left = left[len(tier) :]
    return out


def leak_failures(report: dict, threshold: float) -> list[tuple[str, float]]:
    """(row, gated value) for every row above ``threshold``, by severity."""
    rows = [g for g in report["groups"] if g["gate"] is not None and g["gate"]["value"] > threshold]
    return [(g["name"], g["gate"]["value"]) for g in severity(rows)]


def headline(report: dict, threshold: float | None = None) -> str | None:
    """The decision in one line: pass or fail at ``threshold`` and the main reason (without a
    threshold: the row that leaks most beyond its control). None without the user's key."""
    rows = [g for g in report["groups"] if g["gate"] is not None]
    if report["user"] is None:
        return None
    if not rows:  # e.g. a budget the reference and your key spent (a real-size policy): nothing to decide on
        return None if threshold is None else f"NO DECISION at --max-leak {threshold:g}: {NOTHING_RAN}"
    top = severity(rows)[0]
    value, what = top["gate"]["value"], _what(top)
    if threshold is None:
        return f"most leaked: {top['name']}: {finding(top)} ({what} {value:.3f})"
    if value <= threshold:
        return (f"PASSED --max-leak {threshold:g}: no row leaks more than {threshold:g} beyond its control "
                f"(largest: {top['name']}, {what} {value:.3f})")  # fmt: skip
    return f"FAILED --max-leak {threshold:g}: {reason(report, top)}"


def reason(report: dict, row: dict) -> str:
    """Why ``row`` fails, and what to do: "structure: your code can be read off ... ; seal it ..."."""
    value, what = row["gate"]["value"], _what(row)
    fix = report.get("remedy")
    return f"{row['name']}: {finding(row)} ({what} {value:.3f})" + (f"; {fix}" if fix else "")


def _what(row: dict) -> str:
    return "beyond its control" if row["gate"]["on"] == "beyond-control" else "leakage"


def apply_max_leak(report: dict, threshold: float) -> list[tuple[str, float]]:
    """Add the --max-leak verdict to the report (``max_leak``); returns the failing rows by severity."""
    if report["user"] is None:
        raise PropError("--max-leak needs the user's key and targets", "pass --key-file with --data x,y")
    if not 0 <= threshold <= 1:
        raise PropError(f"--max-leak {threshold} is out of range", "use a leakage in [0, 1], e.g. 0.02")
    failing = leak_failures(report, threshold)
    rows = {g["name"]: g for g in report["groups"]}
    ran = any(g["gate"] is not None for g in report["groups"])
    report["max_leak"] = {
        "threshold": threshold,
        "passed": ran and not failing,  # no row ran: no pass
        "verdict": headline(report, threshold),
        "reason": reason(report, rows[failing[0][0]]) if failing else None,
        "failing": [n for n, _ in failing],
        "rows": [
            {"name": n, "threat": rows[n]["threat"], "value": v, "on": rows[n]["gate"]["on"],
             "why": rows[n]["gate"]["why"], "finding": finding(rows[n])}
            for n, v in failing
        ],
    }  # fmt: skip
    return failing
