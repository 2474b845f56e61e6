"""The vocabulary a JSON file's schema is written in: one ``Rule`` per field (its JSON type, its range,
whether it is required), and the table of what each checkpoint adapter's model spec holds.

No file format of its own and nothing to check with: the bundle format (``prop_cli.bundle.manifest``)
checks files against rules, and each adapter declares its own model spec's fields with them
(``Adapter.manifest_fields``), so the format names no adapter and imports no model code.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

_HEX = re.compile(r"[0-9a-f]*")
_SHA256 = re.compile(r"[0-9a-f]{64}")
MAX_TEXT = 4096  # longest string a rule accepts where it gives no other bound
MAX_DIM = 1 << 24  # largest layer width or input dimension a manifest may claim


@dataclass(frozen=True)
class Rule:
    """One field: JSON ``kind`` (or kinds), ``ok(value)`` with the ``want`` text, and its children."""

    kind: tuple[type, ...]
    want: str
    ok: Callable[[Any], bool] | None = None
    required: bool | tuple[str, ...] = True  # True, False, or the modes in which it is required
    nullable: bool = False
    fields: dict[str, Rule] | None = None  # an object with these fields, others refused
    open: bool = False  # with ``fields``: other fields allowed (an adapter's own spec)
    items: Rule | None = None  # a list of these
    values: Rule | None = None  # an object of free names (``key_ok``) -> these
    key_ok: Callable[[str], bool] | None = None
    variants: tuple[str, dict[str, dict[str, Rule]]] | None = None  # (field, value -> extra fields)
    min_len: int = 0
    max_len: int = 1 << 16


def optional(rule: Rule, required: bool | tuple[str, ...] = False, nullable: bool = False) -> Rule:
    """``rule`` for a field that is optional (or required only in the given modes)."""
    return replace(rule, required=required, nullable=nullable or rule.nullable)


def integer(lo: int, hi: int, multiple: int = 1) -> Rule:
    more = f", a multiple of {multiple}" if multiple > 1 else ""
    return Rule((int,), f"an integer in {lo}..{hi}{more}", lambda v: lo <= v <= hi and v % multiple == 0)


def number(lo: float, hi: float = math.inf, open_lo: bool = False) -> Rule:
    left = "(" if open_lo else "["

    def ok(v: float) -> bool:
        return math.isfinite(v) and (v > lo if open_lo else v >= lo) and v <= hi

    return Rule((int, float), f"a finite number in {left}{lo}, {hi}]", ok)


def text(max_len: int = MAX_TEXT, nonempty: bool = True) -> Rule:
    return Rule((str,), f"a {'non-empty ' * nonempty}string of at most {max_len} characters",
                lambda v: (bool(v) or not nonempty) and len(v) <= max_len)  # fmt: skip


def choice(options: tuple[str, ...]) -> Rule:
    return Rule((str,), "one of " + ", ".join(repr(o) for o in options), lambda v: v in options)


def hex_string(min_bytes: int, max_bytes: int) -> Rule:
    return Rule((str,), f"lowercase hex of {min_bytes} to {max_bytes} bytes",
                lambda v: min_bytes * 2 <= len(v) <= max_bytes * 2 and len(v) % 2 == 0
                and _HEX.fullmatch(v) is not None)  # fmt: skip


SHA256 = Rule((str,), "a sha256 in lowercase hex (64 characters)", lambda v: _SHA256.fullmatch(v) is not None)
BOOL = Rule((bool,), "true or false")
RECORD = Rule((dict,), "an object (a record; not read when loading)")  # reports: free-form JSON
DIM = integer(1, MAX_DIM)


def obj(fields: dict[str, Rule], **kw: Any) -> Rule:
    return Rule((dict,), "an object", fields=fields, **kw)


def list_of(item: Rule, min_len: int = 0, max_len: int = 1 << 16) -> Rule:
    want = f"a list of {min_len} to {max_len} items"
    return Rule((list,), want, items=item, min_len=min_len, max_len=max_len)


# What each adapter's model spec holds besides "adapter" (a manifest's ``model``), by adapter name:
# handed in by the adapter registry (``prop_adapters.ADAPTERS``, each adapter's ``manifest_fields``)
# when it is imported, and read by the bundle format when it checks a manifest. An adapter this table
# does not know (an extension) is checked for "adapter" only; its rebuild reports the rest.
MODEL_FIELDS: dict[str, dict[str, Rule]] = {}
# What one field's rule cannot say of a model spec (how its fields fit together), by adapter name: the
# spec -> None, or (the field, what is wrong with it).
SpecCheck = Callable[[dict], "tuple[str, str] | None"]
MODEL_CHECKS: dict[str, SpecCheck] = {}


def declare_model_fields(adapter: str, fields: dict[str, Rule], check: SpecCheck | None = None) -> None:
    """Record what adapter ``adapter``'s model spec holds (``MODEL_FIELDS``) and how its fields fit
    together (``MODEL_CHECKS``)."""
    MODEL_FIELDS[adapter] = dict(fields)
    if check is not None:
        MODEL_CHECKS[adapter] = check
