"""Writing what prop writes: never over the user's files without --force, never half a file.

Every output (bundle, export folder, run output, audit JSON and plot, manifest updates) is written
to a temporary sibling and renamed into place, so an interrupted run leaves nothing at the path.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import signal
import tempfile
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

from . import constants as C
from .errors import PropError

# What this process has put in place so far (final paths, in order): the CLI names them if interrupted.
_WRITTEN: list[Path] = []


def written() -> list[Path]:
    return list(_WRITTEN)


def wrote(path: Path) -> None:
    """Record a finished output (called once it is at its final path)."""
    _WRITTEN.append(Path(path))


@contextlib.contextmanager
def uninterrupted() -> Iterator[None]:
    """Hold Ctrl-C until the block ends, so a rename (or a pair of them) is never cut in half."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    old = signal.signal(signal.SIGINT, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)
        if held:
            signal.raise_signal(signal.SIGINT)  # now, to the handler that was there before


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def dump_json(obj: dict) -> str:
    """The one JSON style of prop's files: sorted keys, indented, newline-terminated."""
    return json.dumps(obj, sort_keys=True, indent=2) + "\n"


def check_output(out: Path, force: bool, what: str = "bundle", flag: str = "--out") -> None:
    """Refuse to replace what the user owns without --force; fail early if the place is unwritable."""
    out = Path(out)
    if out.exists() and not force:
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


def _cannot_write(what: str, out: Path, e: OSError, flag: str) -> PropError:
    why = e.strerror or type(e).__name__
    return PropError(
        f"cannot write {what} {out}: no file can be created in {out.resolve().parent} ({why})",
        f"choose another {flag}",
    )


@contextlib.contextmanager
def staged_dir(out: Path, what: str = "bundle", flag: str = "--out") -> Iterator[Path]:
    """A temporary folder beside ``out``, renamed to ``out`` when the block succeeds, removed if not."""
    out = Path(out)
    try:
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.resolve().parent))
    except OSError as e:
        raise _cannot_write(what, out, e, flag) from None
    try:
        yield tmp
        with uninterrupted():
            replace_dir(tmp, out)
            wrote(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def write_file(
    out: Path, write: Callable[[Path], None], what: str = "output", flag: str = "--output"
) -> Path:
    """Call ``write(tmp)`` on a temporary sibling of ``out`` (same suffix), then rename it to ``out``."""
    out = Path(out)
    try:
        fd, name = tempfile.mkstemp(prefix=f".{out.name}.", suffix=out.suffix, dir=out.resolve().parent)
    except OSError as e:
        raise _cannot_write(what, out, e, flag) from None
    os.close(fd)
    tmp = Path(name)
    try:
        write(tmp)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; give what a plain open() would
        with uninterrupted():
            os.replace(tmp, out)
            wrote(out)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return out


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_text(out: Path, text: str, what: str = "output", flag: str = "--output") -> Path:
    return write_file(out, lambda p: p.write_text(text), what, flag)


def replace_dir(new: Path, out: Path) -> None:
    """Move folder ``new`` to ``out``, replacing what is there (a file or a folder). Call it under
    ``uninterrupted()``: between its two renames nothing is at ``out``."""
    if not out.exists():
        os.replace(new, out)
        return
    old = new.with_name(new.name + ".old")
    os.replace(out, old)
    os.replace(new, out)
    if old.is_dir():
        shutil.rmtree(old)
    else:
        old.unlink()
