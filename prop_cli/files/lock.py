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
``put`` and ``delete`` go through the lock held on the folder named or on a folder above it
(``<bundle>/onnx`` through its bundle's); the locks held and the walk below a descriptor are
``descriptors``' (which reads the same way: ``descriptors.opened``).
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

from prop_cli import constants as C
from prop_cli.errors import PropError

from .descriptors import DIR, NOFOLLOW, below, held_at, holding, link_refused, under
from .links import RESTORE, TAMPERED


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
    flags = os.O_RDWR | os.O_CREAT | NOFOLLOW | getattr(os, "O_CLOEXEC", 0)
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
    entry = holding().get(key)
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
        dfd = os.open(folder, DIR)
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
        holding()[key] = [dfd, 1]
        yield dfd
    finally:
        holding().pop(key, None)
        with contextlib.suppress(OSError):
            os.unlink(C.BUNDLE_LOCK, dir_fd=dfd)  # while held: a waiter then sees it is gone and retries
        os.close(fd)  # releases the flock
        os.close(dfd)


def _not_a_link(pfd: int, name: str, rel: str, folder: Path, what: str) -> None:
    """A link where prop writes or deletes a file is a sign of tampering: refused, not replaced."""
    try:
        st = os.stat(name, dir_fd=pfd, follow_symlinks=False)
    except FileNotFoundError:
        return
    if stat.S_ISLNK(st.st_mode):
        raise link_refused(folder, rel, what)


def write_at(dfd: int, rel: str, data: bytes, folder: Path, what: str = "bundle") -> None:
    """Write ``data`` to ``rel`` below the locked folder ``dfd`` (``folder``: its path, for messages),
    atomically (a temporary sibling, flushed, renamed over it), never through a link."""
    with below(dfd, rel, folder, what, create=True) as (pfd, name):
        _not_a_link(pfd, name, rel, folder, what)
        tmp = f".{name}.{os.getpid()}.{threading.get_ident()}.tmp"
        flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | NOFOLLOW | getattr(os, "O_CLOEXEC", 0)
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
        with below(dfd, rel, folder, what, create=False) as (pfd, name):
            _not_a_link(pfd, name, rel, folder, what)
            os.unlink(name, dir_fd=pfd)
    except FileNotFoundError:
        pass


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
    dfd, sub, root = at
    write_at(dfd, under(sub, rel), data, root, "bundle" if sub else what)
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
        dfd, sub, root = at
        remove_at(dfd, under(sub, rel), root, "bundle" if sub else what)
