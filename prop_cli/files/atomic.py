"""Writing what prop writes, never half a file: every output (bundle, export folder, run output, audit JSON
and plot, manifest updates) is written to a temporary sibling and renamed into place, so an interrupted
run leaves nothing at the path; and the outputs this process has put in place, for the CLI to name if
it is interrupted (``written``)."""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
import signal
import stat
import tempfile
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

from prop_cli.errors import PropError

from .descriptors import DIR, NOFOLLOW, below, held_at
from .links import shown

# What this process has put in place so far (final paths, in order): the CLI names them if interrupted.
_WRITTEN: list[Path] = []
# The folder each output was checked in (``check_writable``): {output's absolute path: (st_dev, st_ino)}.
# ``staged_dir`` writes the output only in that folder, wherever its path leads by then.
_CHECKED: dict[str, tuple[int, int]] = {}


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
        if out is not None:  # the folder ``staged_dir`` will open: out's, as named
            st = os.stat(Path(out).absolute().parent)
            _CHECKED[os.path.abspath(out)] = (st.st_dev, st.st_ino)
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


# Folder writes go through descriptors (the output's parent opened once, ``dir_fd`` renames) where the
# system has them; elsewhere (no ``dir_fd`` support) by absolute path, as before.
_FD_OK = {os.open, os.mkdir, os.rename, os.unlink, os.rmdir, os.stat} <= os.supports_dir_fd


@contextlib.contextmanager
def _out_parent(out: Path, what: str, flag: str) -> Iterator[tuple[int | None, Path, bool]]:
    """The folder ``out`` is written in, opened once: its descriptor (None: no ``dir_fd`` here), its
    path and whether it is (or lies below) a bundle this thread has locked, whose descriptor it then is
    reached from (every part below the locked folder opened with O_NOFOLLOW: a link is refused)."""
    parent = out.absolute().parent
    at = held_at(parent) if _FD_OK else None
    if at is not None:
        dfd, sub, root = at
        if not sub:
            yield dfd, parent, True
            return
        with below(dfd, f"{sub}/{out.name}", root, what, create=False) as (pfd, _):
            yield pfd, parent, True
        return
    if not _FD_OK:
        yield None, parent, False
        return
    try:
        pfd = os.open(parent, DIR)
    except OSError as e:
        raise _cannot_write(what, out, e, flag, parent) from None
    try:
        yield pfd, parent, False
    finally:
        os.close(pfd)


def _by_descriptor(fd: int, plain: Path) -> Path:
    """A path that names the folder open as ``fd`` whatever happens to the folders above it
    (``/proc/<pid>/fd/<fd>``, where the system has one; children of this process can use it too), else
    ``plain``."""
    proc = Path(f"/proc/{os.getpid()}/fd/{fd}")
    try:
        st, own = os.stat(proc), os.fstat(fd)
    except OSError:
        return plain
    return proc if (st.st_dev, st.st_ino) == (own.st_dev, own.st_ino) else plain


def _still_there(
    pfd: int, parent: Path, out: Path, what: str, flag: str, checked: tuple[int, int] | None = None
) -> None:
    """The folder open as ``pfd`` is the one ``out`` was checked in (``checked``, from
    ``check_writable``), or, without ``checked``, still the one its path names: one that was moved, or
    swapped for a link, is refused in one line; nothing is put there. (The renames go through the
    descriptor: even a swap after this check moves nothing elsewhere.)"""
    own = os.fstat(pfd)
    try:
        if checked is None:
            st = os.stat(parent)
            checked = (st.st_dev, st.st_ino)
        same = checked == (own.st_dev, own.st_ino)
    except OSError:
        same = False
    if same:
        return
    now = f", now a symbolic link to {shown(os.readlink(parent))}" if os.path.islink(parent) else ""
    raise PropError(
        f"cannot write {what} {out}: folder {parent} was replaced or moved while prop wrote it{now}; "
        "nothing was written there and nothing outside it",
        f"check what else changes {parent}, then run the command again (or choose another {flag})",
    )


@contextlib.contextmanager
def staged_dir(out: Path, what: str = "bundle", flag: str = "--out") -> Iterator[Path]:
    """A temporary folder beside ``out``, renamed to ``out`` when the block succeeds, removed if not.

    The folder ``out`` goes in is opened once, first, and must be the folder the command checked
    (``check_output``/``check_writable``); the stage is made, renamed and (if the block fails) removed
    through that descriptor, and what was at ``out`` is removed through it too: a folder on the way
    swapped for a link while the command runs is not followed. The path yielded names the stage by its
    descriptor where the system has one (``/proc/<pid>/fd/<fd>``), so that what the block writes in it
    goes there, wherever the folders above it are moved. If the parent folder no longer is the one its
    path names when the block ends, the command is refused (``_still_there``); under a bundle's lock,
    the locked folder is the one written (as ``lock.write_at`` writes)."""
    with _staged(Path(out), what, flag, file=False) as tmp:
        yield tmp


def write_file(
    out: Path, write: Callable[[Path], None], what: str = "output", flag: str = "--output"
) -> Path:
    """Call ``write(tmp)`` on a temporary file named as ``out`` (same suffix) in a stage folder beside
    it, then rename it to ``out``: through descriptors, as ``staged_dir`` writes a folder."""
    with _staged(Path(out), what, flag, file=True) as tmp:
        write(tmp)
    return Path(out)


@contextlib.contextmanager
def _staged(out: Path, what: str, flag: str, file: bool) -> Iterator[Path]:
    """``staged_dir`` (``file``: a file named as ``out`` in the stage, renamed to ``out``, the stage
    then removed)."""
    if out.name in ("", ".", ".."):
        out = out.resolve()
    checked = _CHECKED.pop(os.path.abspath(out), None)
    with _out_parent(out, what, flag) as (pfd, parent, locked):
        if pfd is not None and checked is not None:
            _still_there(pfd, parent, out, what, flag, checked)
        name = f".{out.name}.{secrets.token_hex(4)}.tmp"
        here = name if pfd is not None else str(parent / name)
        target = out.name if pfd is not None else str(parent / out.name)
        try:
            os.mkdir(here, 0o700, dir_fd=pfd)  # as mkdtemp: the stage is this user's alone
        except OSError as e:
            raise _cannot_write(what, out, e, flag, parent) from None
        sfd = None
        try:
            if pfd is not None:
                sfd = os.open(name, DIR | NOFOLLOW, dir_fd=pfd)
            stage = _by_descriptor(sfd, parent / name) if sfd is not None else parent / name
            if file:  # there even if ``write`` writes nothing (as mkstemp's file was)
                os.close(os.open(stage / out.name, os.O_WRONLY | os.O_CREAT | os.O_EXCL | NOFOLLOW, 0o666))
            yield stage / out.name if file else stage
            with uninterrupted():
                if pfd is not None and not locked:
                    _still_there(pfd, parent, out, what, flag)
                if file:
                    os.rename(f"{here}/{out.name}", target, src_dir_fd=pfd, dst_dir_fd=pfd)
                    os.rmdir(here, dir_fd=pfd)
                else:
                    _replace_at(pfd, here, target)
                wrote(out)
        except BaseException:
            with contextlib.suppress(OSError):
                _rmtree_at(pfd, here)
            raise
        finally:
            if sfd is not None:
                os.close(sfd)


def write_text(out: Path, text: str, what: str = "output", flag: str = "--output") -> Path:
    return write_file(out, lambda p: p.write_text(text), what, flag)


def replace_dir(new: Path, out: Path) -> None:
    """Move folder ``new`` to ``out`` (both in one folder), replacing what is there (a file or a folder),
    through a descriptor of that folder. Call it under ``uninterrupted()``: between its two renames
    nothing is at ``out``."""
    new, out = Path(new), Path(out)
    if not _FD_OK:
        _replace_at(None, str(new), str(out))
        return
    pfd = os.open(out.absolute().parent, DIR)
    try:
        _replace_at(pfd, new.name, out.name)
    finally:
        os.close(pfd)


def _replace_at(pfd: int | None, new: str, out: str) -> None:
    """``replace_dir`` below the folder open as ``pfd`` (None: ``new``, ``out`` are paths): what was at
    ``out`` is renamed aside, then removed without following any link in it (a link at ``out``: the
    link goes, not what it names)."""
    try:
        os.stat(out, dir_fd=pfd, follow_symlinks=False)
    except FileNotFoundError:
        os.rename(new, out, src_dir_fd=pfd, dst_dir_fd=pfd)
        return
    old = new + ".old"
    os.rename(out, old, src_dir_fd=pfd, dst_dir_fd=pfd)
    os.rename(new, out, src_dir_fd=pfd, dst_dir_fd=pfd)
    _rmtree_at(pfd, old)


def _rmtree_at(pfd: int | None, name: str) -> None:
    """Remove ``name`` below the folder open as ``pfd`` (a folder with all it holds, or a file or link),
    each folder opened with O_NOFOLLOW: nothing a link names is removed."""
    st = os.stat(name, dir_fd=pfd, follow_symlinks=False)
    if not stat.S_ISDIR(st.st_mode):
        os.unlink(name, dir_fd=pfd)
        return
    if pfd is None:
        shutil.rmtree(name)  # no dir_fd here: shutil's own guard against links
        return
    fd = os.open(name, DIR | NOFOLLOW, dir_fd=pfd)
    try:
        with os.scandir(fd) as it:
            entries = [e.name for e in it]
        for entry in entries:
            _rmtree_at(fd, entry)
    finally:
        os.close(fd)
    os.rmdir(name, dir_fd=pfd)
