"""The audit's probes (contract: ``base.Probe``). ``PROBES`` is the registry, in report order: a new
probe is one new file exposing ``PROBE`` and one line here."""

from __future__ import annotations

from prop_cli.errors import PropError

from . import blackbox, cross_user, drift, fewshot, hamming, latent, null, random_keys, relaxed, structure
from .base import Group, Probe, ProbeContext, Reference

PROBES: list[Probe] = [
    null.PROBE,
    random_keys.PROBE,
    hamming.PROBE,
    blackbox.PROBE,
    structure.PROBE,
    drift.PROBE,
    relaxed.PROBE,
    latent.PROBE,
    fewshot.PROBE,
    cross_user.PROBE,
]

__all__ = ["PROBES", "Group", "Probe", "ProbeContext", "Reference", "names", "probe_named", "select"]


def names() -> list[str]:
    return [p.name for p in PROBES]


def probe_named(name: str) -> Probe:
    for p in PROBES:
        if p.name == name:
            return p
    raise PropError(f"--probes: unknown probe {name!r}", "use a list of: " + ", ".join(names()))


def select(probes: list[str] | None = None, search: list[str] | None = None) -> list[str]:
    """Probe names from ``--probes`` (None: the defaults) or the older ``--search`` (the black-box key
    probes plus the given searches)."""
    if probes is not None and search is not None:
        raise PropError("--probes and --search both given", "use --probes (--search is its older form)")
    if search is not None:
        searches = [p.name for p in PROBES if p.kind == "search"]
        for s in search:
            if s not in searches:
                raise PropError(f"--search {s!r} is not a search", "use " + ", ".join(searches) + " or none")
        return [
            p.name for p in PROBES if (p.kind == "key" and p.default and not p.white_box) or p.name in search
        ]
    if probes is None:
        return [p.name for p in PROBES if p.default]
    for p in probes:
        probe_named(p)
    return [p.name for p in PROBES if p.name in probes]
