"""One writer at a time (issue 42, item 4): every command that rewrites a bundle holds an exclusive lock
on it, and writes through the folder it locked.

``bundle_lock(folder)`` opens the bundle folder once, takes an ``flock`` on ``C.BUNDLE_LOCK`` inside it
(the file holds the writer's pid while the lock is held and is removed when it is released), and yields
the folder's descriptor. Another prop process (or thread) that wants it waits up to
``C.BUNDLE_LOCK_WAIT_S`` and is then refused in one line naming the pid that holds it; nothing is
written. Nested use in one thread (add-user's ``rewrite_records`` inside ``api.add_user``) reuses the
lock held. ``write_at`` and ``remove_at`` write and delete relative to that descriptor, each folder
below it opened with ``O_NOFOLLOW``: a bundle folder (or ``users/``) swapped for a link while the
command runs is not followed (the write goes to the folder that was locked, or is refused in one line).
``put``, ``delete`` and ``opened`` go through the lock held on the folder named or on a folder above it
(``<bundle>/onnx`` through its bundle's), and ``opened`` reads a file below a folder with no lock the
same way, from a descriptor of that folder: no part below it is followed if it is a link.
"""

from __future__ import annotations

import contextlib
import errno
import os
import stat
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

from prop_cli import constants as C
from prop_cli.errors import PropError

from .links import RESTORE, TAMPERED, shown

_HELD = threading.local()  # .locks: {folder's absolute path, as named: [dir fd, depth]} of this thread
_DIR = os.O_RDONLY | getattr(os, "O_DIRECTORY", 0) | getattr(os, "O_CLOEXEC", 0)
_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)


def _held() -> dict[str, list[int]]:
    if not hasattr(_HELD, "locks"):
        _HELD.locks = {}
    return _HELD.locks


def held(folder: Path) -> int | None:
    """The descriptor of ``folder`` if this thread holds its lock (None: it does not)."""
    entry = _held().get(os.path.abspath(folder))
    return entry[0] if entry else None


def _holder(fd: int) -> str:
    """Who holds the lock, from what its file says: "pid N", or "another prop process"."""
    with contextlib.suppress(OSError, ValueError):
        text = os.pread(fd, 32, 0).decode("ascii").strip()
        if text.isdigit():
            return f"pid {int(text)}"
    return "another prop process"


def _cannot(folder: Path, e: OSError, what: str) -> PropError:
    return PropError(
        f"{what} {folder} cannot be written in place ({e.strerror or type(e).__name__})",
        "make the folder writable, or work on a copy of it",
    )


def _acquire(dfd: int, folder: Path, what: str, wait: float) -> int | None:
    """The lock file's descriptor, once its flock is held and it is still the file at its name (None:
    the folder is not writable, so there is nothing to lock)."""
    import fcntl

    deadline = time.monotonic() + wait
    flags = os.O_RDWR | os.O_CREAT | _NOFOLLOW | getattr(os, "O_CLOEXEC", 0)
    while True:
        try:
            fd = os.open(C.BUNDLE_LOCK, flags, 0o600, dir_fd=dfd)
        except FileNotFoundError:  # the folder was removed (replaced) while this command waited
            raise PropError(
                f"{what} {folder} was replaced or removed while this command waited to write it",
                "run the command again",
            ) from None
        except OSError as e:
            if e.errno == errno.ELOOP:
                raise PropError(
                    f"{what} {folder}: {C.BUNDLE_LOCK} is a symbolic link; prop reads and writes nothing "
                    f"through links: {TAMPERED}",
                    RESTORE,
                ) from None
            if e.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
                return None  # a folder this user cannot write: no writer can race here; the write says why
            raise _cannot(folder, e, what) from None
        opened = os.fstat(fd)
        if not stat.S_ISREG(opened.st_mode) or opened.st_nlink != 1:
            # A hard link to another file (the manifest, a record, a file outside the bundle) or a FIFO
            # put there by whoever made the bundle: writing the pid would truncate that file.
            os.close(fd)
            raise PropError(
                f"{what} {folder}: {C.BUNDLE_LOCK} is not a plain file of its own (a hard link or a special "
                f"file); prop writes nothing through it: {TAMPERED}",
                RESTORE,
            )
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(fd)
            os.close(fd)
            if time.monotonic() >= deadline:
                raise PropError(
                    f"{what} {folder} is being written by another prop command ({holder}); nothing was "
                    "written",
                    "wait for that command to finish, then run this one again",
                ) from None
            time.sleep(0.05)
            continue
        try:  # the file the lock is on must still be the one at the name (a releaser removes it)
            st = os.stat(C.BUNDLE_LOCK, dir_fd=dfd, follow_symlinks=False)
        except FileNotFoundError:
            os.close(fd)
            continue
        own = os.fstat(fd)
        if (st.st_dev, st.st_ino) != (own.st_dev, own.st_ino):
            os.close(fd)
            continue
        return fd


@contextlib.contextmanager
def bundle_lock(folder: Path, what: str = "bundle", wait: float | None = None) -> Iterator[int | None]:
    """Hold the write lock of the bundle at ``folder`` and yield its descriptor (None where there is
    nothing to lock: no such folder yet, one this user cannot write, or no flock on this system)."""
    folder = Path(folder)
    key = os.path.abspath(folder)  # as named, not resolved: a link swapped in later is not the key
    entry = _held().get(key)
    if entry is not None:  # this thread holds it already: a nested write of the same command
        entry[1] += 1
        try:
            yield entry[0]
        finally:
            entry[1] -= 1
        return
    try:
        import fcntl  # noqa: F401 - POSIX only
    except ImportError:
        yield None
        return
    try:
        dfd = os.open(folder, _DIR)
    except (FileNotFoundError, NotADirectoryError):  # nothing to lock: the command's own check says why
        yield None
        return
    try:
        fd = _acquire(dfd, folder, what, C.BUNDLE_LOCK_WAIT_S if wait is None else wait)
    except BaseException:
        os.close(dfd)
        raise
    if fd is None:
        os.close(dfd)
        yield None
        return
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        _held()[key] = [dfd, 1]
        yield dfd
    finally:
        _held().pop(key, None)
        with contextlib.suppress(OSError):
            os.unlink(C.BUNDLE_LOCK, dir_fd=dfd)  # while held: a waiter then sees it is gone and retries
        os.close(fd)  # releases the flock
        os.close(dfd)


def held_at(folder: Path) -> tuple[int, str, Path] | None:
    """The lock this thread holds on ``folder`` or on the nearest folder above it (as named): that
    folder's descriptor, the path of ``folder`` below it ("" for itself) and its path; None if none."""
    path = here = os.path.abspath(folder)
    locks = _held()
    while True:
        entry = locks.get(here)
        if entry is not None:
            below = "" if here == path else os.path.relpath(path, here).replace(os.sep, "/")
            return entry[0], below, Path(here)
        up = os.path.dirname(here)
        if up == here:
            return None
        here = up


def _link_refused(folder: Path, rel: str, what: str, while_writing: bool = True) -> PropError:
    when = " (put there while prop wrote the bundle)" if while_writing else ""
    return PropError(
        f"{what} {folder}: {shown(rel)} is a symbolic link{when}; prop reads and writes nothing through "
        f"links: {TAMPERED}",
        RESTORE,
    )


@contextlib.contextmanager
def _parent(
    dfd: int, rel: str, folder: Path, what: str, create: bool, while_writing: bool = True
) -> Iterator[tuple[int, str]]:
    """The descriptor of ``rel``'s folder below ``dfd`` (each part opened with O_NOFOLLOW, created if
    ``create``) and ``rel``'s last part."""
    *parts, name = [p for p in rel.split("/") if p not in ("", ".")]
    if ".." in parts or name == "..":  # below ``dfd`` only (manifests and exports never name one)
        raise PropError(f"{what} {folder}: {shown(rel)} leaves the folder: {TAMPERED}", RESTORE)
    fds = [dfd]
    try:
        for i, part in enumerate(parts):
            if create:
                with contextlib.suppress(FileExistsError):
                    os.mkdir(part, 0o777, dir_fd=fds[-1])
            try:
                fds.append(os.open(part, _DIR | _NOFOLLOW, dir_fd=fds[-1]))
            except OSError as e:
                if e.errno in (errno.ELOOP, errno.ENOTDIR):
                    raise _link_refused(folder, "/".join(parts[: i + 1]), what, while_writing) from None
                raise
        yield fds[-1], name
    finally:
        for fd in fds[1:]:
            os.close(fd)


def _not_a_link(pfd: int, name: str, rel: str, folder: Path, what: str) -> None:
    """A link where prop writes or deletes a file is a sign of tampering: refused, not replaced."""
    try:
        st = os.stat(name, dir_fd=pfd, follow_symlinks=False)
    except FileNotFoundError:
        return
    if stat.S_ISLNK(st.st_mode):
        raise _link_refused(folder, rel, what)


def write_at(dfd: int, rel: str, data: bytes, folder: Path, what: str = "bundle") -> None:
    """Write ``data`` to ``rel`` below the locked folder ``dfd`` (``folder``: its path, for messages),
    atomically (a temporary sibling, flushed, renamed over it), never through a link."""
    with _parent(dfd, rel, folder, what, create=True) as (pfd, name):
        _not_a_link(pfd, name, rel, folder, what)
        tmp = f".{name}.{os.getpid()}.{threading.get_ident()}.tmp"
        flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | _NOFOLLOW | getattr(os, "O_CLOEXEC", 0)
        fd = os.open(tmp, flags, 0o666, dir_fd=pfd)
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, name, src_dir_fd=pfd, dst_dir_fd=pfd)
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(tmp, dir_fd=pfd)
            raise


def remove_at(dfd: int, rel: str, folder: Path, what: str = "bundle") -> None:
    """Delete ``rel`` below the locked folder ``dfd`` if it is there, never through a linked folder."""
    try:
        with _parent(dfd, rel, folder, what, create=False) as (pfd, name):
            _not_a_link(pfd, name, rel, folder, what)
            os.unlink(name, dir_fd=pfd)
    except FileNotFoundError:
        pass


def _below(below: str, rel: str) -> str:
    return f"{below}/{rel}" if below else rel


def put(folder: Path, rel: str, data: bytes, what: str = "bundle", output: bool = False) -> None:
    """Write ``folder / rel`` atomically: through the locked folder when this thread holds the lock of
    ``folder`` or of a folder above it (``bundle_lock``), else by path (a folder being staged, that no
    one else sees), never through a link. ``output``: name it among what this process wrote
    (``atomic.written``)."""
    from .atomic import write_file, wrote
    from .links import no_links

    at = held_at(folder)
    if at is None:
        write_file(no_links(folder, rel, what), lambda p: p.write_bytes(data), what, "BUNDLE")
        return
    dfd, below, root = at
    write_at(dfd, _below(below, rel), data, root, "bundle" if below else what)
    if output:
        wrote(Path(folder) / rel)


def delete(folder: Path, rel: str, what: str = "bundle") -> None:
    """Delete ``folder / rel`` if it is there: through the locked folder when this thread holds the lock
    of ``folder`` or of a folder above it, else by path; never through a linked folder."""
    from .links import remove_inside

    at = held_at(folder)
    if at is None:
        remove_inside(folder, rel, what)
    else:
        dfd, below, root = at
        remove_at(dfd, _below(below, rel), root, "bundle" if below else what)


@contextlib.contextmanager
def opened(folder: Path, rel: str, what: str = "bundle") -> Iterator[BinaryIO]:
    """``folder / rel`` open for reading, reached from a descriptor of ``folder`` (the lock's, if this
    thread holds it or one above it; else ``folder`` opened now, as named) with every part below it
    opened with O_NOFOLLOW: a link anywhere below ``folder``, there from the start or swapped in since a
    check, is refused in one line, never followed. FileNotFoundError where a part is missing."""
    at = held_at(folder)
    if at is None:
        dfd, below, root = os.open(folder, _DIR), "", Path(folder)
    else:
        dfd, below, root = at
        what = "bundle" if below else what
    rel = _below(below, rel)
    try:
        with _parent(dfd, rel, root, what, create=False, while_writing=False) as (pfd, name):
            try:
                # O_NONBLOCK: a FIFO swapped in is refused below, not waited on (no effect on files)
                flags = os.O_RDONLY | _NOFOLLOW | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_NONBLOCK", 0)
                fd = os.open(name, flags, dir_fd=pfd)
            except OSError as e:
                if e.errno == errno.ELOOP:
                    raise _link_refused(root, rel, what, while_writing=False) from None
                raise
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                os.close(fd)
                raise PropError(f"{what} {root}: {shown(rel)} is not a plain file: {TAMPERED}", RESTORE)
            with os.fdopen(fd, "rb") as f:
                yield f
    finally:
        if at is None:
            os.close(dfd)


def read(folder: Path, rel: str, what: str = "bundle", limit: int | None = None) -> bytes:
    """The bytes of ``folder / rel``, read as ``opened`` reads them (no link below ``folder`` followed);
    ``limit``: at most that many bytes are read (a caller refuses a file that reaches it)."""
    with opened(folder, rel, what) as f:
        return f.read() if limit is None else f.read(limit)


def sha256_inside(folder: Path, rel: str, what: str = "bundle") -> str:
    """The sha256 of ``folder / rel``, read as ``opened`` reads it."""
    import hashlib

    h = hashlib.sha256()
    with opened(folder, rel, what) as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()
