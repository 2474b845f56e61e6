"""Nothing through a link: a bundle is a folder of plain files; a symbolic link in it would make prop read,
write or delete outside it (issue 31: `users/` linked elsewhere, add-user wrote its record there and
remove-user deleted a file there). Links are refused when a bundle is read (bundle.read.check_tree), and
checked again right before each write or delete inside one: the folder may change while a command runs
(add-user trains for minutes between its read and its write)."""

from __future__ import annotations

import os
import stat
from pathlib import Path

from prop_cli.errors import PropError

TAMPERED = "the bundle may have been tampered with"
RESTORE = "restore it from a trusted copy (prop never writes links, code or unlisted files in a bundle)"


def shown(text: str, width: int = 80) -> str:
    """A name or path an attacker may have chosen, safe on a one-line error (printable, cut short)."""
    s = text if text.isprintable() else repr(text)
    return s if len(s) <= width else s[: width - 3] + "..."


def link_error(root: Path, link: Path, what: str = "bundle") -> PropError:
    """The one line for a symbolic link met inside ``root``, naming it and where it points."""
    try:
        target = shown(os.readlink(link))
    except OSError:
        target = "?"
    return PropError(
        f"{what} {root}: {shown(link.relative_to(root).as_posix())} is a symbolic link (to {target}); "
        f"prop reads and writes nothing through links: {TAMPERED}",
        RESTORE,
    )


def no_links(root: Path, rel: str | Path, what: str = "bundle") -> Path:
    """``root / rel`` once no part of ``rel`` (each folder below ``root``, and the entry itself) is a
    symbolic link; a one-line PropError naming the link otherwise. Parts not there yet are fine: prop
    creates them as plain folders and files."""
    root, here = Path(root), Path(root)
    for part in Path(rel).parts:
        here = here / part
        try:
            st = os.lstat(here)
        except FileNotFoundError:
            break
        if stat.S_ISLNK(st.st_mode):
            raise link_error(root, here, what)
    return root / rel


def write_inside(root: Path, rel: str, data: bytes, what: str = "bundle") -> Path:
    """Write ``data`` to ``root / rel`` (its folder created if absent), never through a link: the path
    is checked (``no_links``) and the file opened with O_NOFOLLOW where the system has it."""
    path = no_links(root, rel, what)
    path.parent.mkdir(parents=True, exist_ok=True)
    flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_BINARY", 0)
    try:
        fd = os.open(path, flags, 0o666)
    except OSError:
        no_links(root, rel, what)  # a link put there since the check: name it
        raise
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    return path


def remove_inside(root: Path, rel: str, what: str = "bundle") -> None:
    """Delete ``root / rel`` if it is there, never through a linked folder (``no_links``)."""
    no_links(root, rel, what).unlink(missing_ok=True)
