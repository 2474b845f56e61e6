"""Folders by descriptor: the folders this thread holds open (the bundles it has locked:
``lock.bundle_lock`` registers them here), the walk below one with each part opened ``O_NOFOLLOW``
(``below``), and prop's reads of a bundle's files that way (``opened``, ``read``, ``sha256_inside``):
no link below the folder is followed, there from the start or swapped in since a check (issue 42)."""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import stat
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

from prop_cli.errors import PropError

from .links import RESTORE, TAMPERED, shown

_HELD = threading.local()  # .locks: {folder's absolute path, as named: [dir fd, depth]} of this thread
DIR = os.O_RDONLY | getattr(os, "O_DIRECTORY", 0) | getattr(os, "O_CLOEXEC", 0)
NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)


def holding() -> dict[str, list[int]]:
    """This thread's locks, as ``lock.bundle_lock`` registers them: {folder's absolute path, as named:
    [its descriptor, how deep the lock is taken]}."""
    if not hasattr(_HELD, "locks"):
        _HELD.locks = {}
    return _HELD.locks


def held(folder: Path) -> int | None:
    """The descriptor of ``folder`` if this thread holds its lock (None: it does not)."""
    entry = holding().get(os.path.abspath(folder))
    return entry[0] if entry else None


def held_at(folder: Path) -> tuple[int, str, Path] | None:
    """The lock this thread holds on ``folder`` or on the nearest folder above it (as named): that
    folder's descriptor, the path of ``folder`` below it ("" for itself) and its path; None if none."""
    path = here = os.path.abspath(folder)
    locks = holding()
    while True:
        entry = locks.get(here)
        if entry is not None:
            sub = "" if here == path else os.path.relpath(path, here).replace(os.sep, "/")
            return entry[0], sub, Path(here)
        up = os.path.dirname(here)
        if up == here:
            return None
        here = up


def link_refused(folder: Path, rel: str, what: str, while_writing: bool = True) -> PropError:
    when = " (put there while prop wrote the bundle)" if while_writing else ""
    return PropError(
        f"{what} {folder}: {shown(rel)} is a symbolic link{when}; prop reads and writes nothing through "
        f"links: {TAMPERED}",
        RESTORE,
    )


def under(sub: str, rel: str) -> str:
    """``rel`` below the folder ``sub`` ("" for the folder itself)."""
    return f"{sub}/{rel}" if sub else rel


@contextlib.contextmanager
def below(
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
                fds.append(os.open(part, DIR | NOFOLLOW, dir_fd=fds[-1]))
            except OSError as e:
                if e.errno in (errno.ELOOP, errno.ENOTDIR):
                    raise link_refused(folder, "/".join(parts[: i + 1]), what, while_writing) from None
                raise
        yield fds[-1], name
    finally:
        for fd in fds[1:]:
            os.close(fd)


@contextlib.contextmanager
def opened(folder: Path, rel: str, what: str = "bundle") -> Iterator[BinaryIO]:
    """``folder / rel`` open for reading, reached from a descriptor of ``folder`` (the lock's, if this
    thread holds it or one above it; else ``folder`` opened now, as named) with every part below it
    opened with O_NOFOLLOW: a link anywhere below ``folder``, there from the start or swapped in since a
    check, is refused in one line, never followed. FileNotFoundError where a part is missing."""
    at = held_at(folder)
    if at is None:
        dfd, sub, root = os.open(folder, DIR), "", Path(folder)
    else:
        dfd, sub, root = at
        what = "bundle" if sub else what
    rel = under(sub, rel)
    try:
        with below(dfd, rel, root, what, create=False, while_writing=False) as (pfd, name):
            try:
                # O_NONBLOCK: a FIFO swapped in is refused below, not waited on (no effect on files)
                flags = os.O_RDONLY | NOFOLLOW | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_NONBLOCK", 0)
                fd = os.open(name, flags, dir_fd=pfd)
            except OSError as e:
                if e.errno == errno.ELOOP:
                    raise link_refused(root, rel, what, while_writing=False) from None
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
    h = hashlib.sha256()
    with opened(folder, rel, what) as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()
