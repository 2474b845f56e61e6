"""Where a command may write: never over what the user owns (without --force; with it, anything but prop's
own output of the command's kind: ``kinds``), never over or inside what the same command reads."""

from __future__ import annotations

import os
from pathlib import Path

from prop_cli import constants as C
from prop_cli.errors import PropError

from .atomic import check_writable
from .kinds import BUNDLE, OutputKind, check_replaceable


def check_output(
    out: Path, force: bool, what: str = "bundle", flag: str = "--out", kind: OutputKind = BUNDLE
) -> None:
    """Refuse to replace what the user owns (without --force; with it, anything but prop's own ``kind``
    of output), and fail early if nothing can be written there."""
    out = Path(out)
    if check_replaceable(out, kind, flag) and not force:
        # Named for both callers: the command line's flags, and the Python API's force= parameter.
        raise PropError(
            f"{what} {out} already exists",
            f"choose another {flag} or pass --force to replace it (force=True in Python)",
        )
    parent = out.resolve().parent
    if not parent.is_dir():
        raise PropError(f"cannot write {what} {out}: folder {parent} does not exist", "create it first")
    if not os.access(parent, os.W_OK):
        raise PropError(
            f"cannot write {what} {out}: folder {parent} is not writable", f"choose another {flag}"
        )
    check_writable(parent, what, flag, out, as_folder=kind.folder)


def _same(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)  # hard links and symlinks too
    except OSError:
        return False


def check_not_input(
    out: Path, flag: str, inputs: list, inside_ok: list | None = None
) -> None:
    """Refuse an output that is one of the same command's inputs, holds one (replacing a folder deletes
    what is in it) or lies inside an input bundle or export (whose files prop checks), ``--force`` or
    not: a command never destroys what it reads. ``inside_ok``: input folders an output may sit inside
    (an export's default place in its bundle). ``inputs`` may hold None and hub paths (skipped)."""
    out = Path(out).resolve()
    for given in inputs:
        if given is None or str(given).startswith("hf://"):
            continue
        src = Path(given).resolve()
        holds = src == out or out in src.parents or _same(src, out)
        inside = src in out.parents and not any(Path(p).resolve() == src for p in inside_ok or [])
        checked = src.is_dir() and any((src / f).is_file() for f in (C.MANIFEST, C.EXPORT_META))
        if holds or (inside and checked):
            why = "is" if src == out or _same(src, out) else ("holds" if holds else "is inside")
            raise PropError(
                f"{flag} {out} {why} this command's input {given}",
                f"write to another {flag}: prop never replaces what the same command reads, --force or not",
            )
