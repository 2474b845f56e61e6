"""Writing what prop writes, never half a file: every output (bundle, export folder, run output, audit JSON
and plot, manifest updates) is written to a temporary sibling and renamed into place, so an interrupted
run leaves nothing at the path; and the outputs this process has put in place, for the CLI to name if
it is interrupted (``written``)."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import tempfile
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

from prop_cli.errors import PropError

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


def check_writable(
    folder: Path, what: str, flag: str, out: Path | None = None, as_folder: bool = True
) -> None:
    """Create and remove a temporary entry (a folder, or a file) in ``folder``, as the write of ``out``
    (default: ``folder`` itself, rewritten in place) will: a folder that refuses it (read-only, /proc,
    another owner's) fails now, before any work, not after it."""
    try:
        if as_folder:
            os.rmdir(tempfile.mkdtemp(prefix=".prop-check.", suffix=".tmp", dir=folder))
        else:
            fd, name = tempfile.mkstemp(prefix=".prop-check.", suffix=".tmp", dir=folder)
            os.close(fd)
            os.unlink(name)
    except OSError as e:
        if out is not None:
            raise _cannot_write(what, Path(out), e, flag, Path(folder)) from None
        raise PropError(
            f"{flag} {folder}: the {what} cannot be written in place ({e.strerror or type(e).__name__})",
            "make the folder writable, or work on a copy of it",
        ) from None


def _cannot_write(what: str, out: Path, e: OSError, flag: str, folder: Path | None = None) -> PropError:
    why = e.strerror or type(e).__name__
    where = folder if folder is not None else out.resolve().parent
    return PropError(
        f"cannot write {what} {out}: no file can be created in {where} ({why})",
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
    if old.is_dir() and not old.is_symlink():  # a link to a folder: the link goes, not what it names
        shutil.rmtree(old)
    else:
        old.unlink()
