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
import stat
import tempfile
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
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


# ---- What --force may replace -------------------------------------------------------------------
# --force replaces only what prop itself writes at that kind of path, never anything else the user put
# there (issue 28: `--out folder --force` deleted a folder that was not a bundle, with its files). Each
# command names its kind; a recogniser returns None for prop's own output (or an empty folder: nothing in
# it to lose), else what is there, in words, for the one-line refusal. Per command:
#   personalize --out         BUNDLE: a folder with prop's manifest.json, of any format version (a newer
#                             prop's too), holding nothing prop did not write (its listed files and
#                             records, its ONNX export, the card and signature `prop push` uploads).
#   export --onnx [--out]     EXPORT: a folder with prop's export.json, holding only what it lists.
#   export --peft             PEFT: a folder holding only adapter_config.json (a LoRA) and its weights.
#   run --output              ARRAY: a .npy array file (what prop run writes).
#   keygen PATH               KEY: a file of a key's size (4 to 128 bytes); the old key is lost.
#   attack --json / --plot    AUDIT_REPORT: a prop-audit JSON report; PLOT: a PNG drawn by matplotlib.
#   eval --video              nothing: a new folder only (run.rollout.check_video).
# add-user, remove-user, enrol and attack --record rewrite a bundle in place (no --force); push stages in
# a temporary folder and writes nothing of the user's; formats and inspect print only.


@dataclass(frozen=True)
class OutputKind:
    """What a command writes at a path, and how to tell it from what is not prop's."""

    replaces: str  # what --force replaces, for messages: "a prop bundle (...)"
    folder: bool  # written as a folder (``staged_dir``), else as a file (``write_file``)
    recognise: Callable[[Path], str | None]  # None: prop's own output; else what is at the path


def _read_json(path: Path) -> object:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):  # absent, unreadable, not JSON (UnicodeDecodeError is a ValueError)
        return None


def _names(paths: list[str]) -> str:
    """A few names, each on the one line an error has."""
    shown = [n if n.isprintable() else repr(n) for n in paths[:3]]
    return ", ".join(shown) + (f" and {len(paths) - 3} more" if len(paths) > 3 else "")


def _entries(folder: Path) -> list[str]:
    with os.scandir(folder) as it:
        return sorted(e.name + ("/" if e.is_dir(follow_symlinks=False) else "") for e in it)


def _not_a(path: Path, name: str) -> str:
    """What is at ``path`` that is not ``name`` (a prop bundle, a key file, ...)."""
    if path.is_dir():
        entries = _entries(path)
        return f"a folder that is not {name} (it holds {_names(entries)})" if entries else "an empty folder"
    if path.is_file():
        return f"a file, not {name}"
    return f"something that is neither a file nor a folder, not {name}"


def _unlisted(root: Path, known: set[str], own_folders: dict[str, OutputKind] | None = None) -> list[str]:
    """Files under ``root`` that are not in ``known`` (paths relative to it), outside folders that are
    prop's own output of their kind (a bundle's ONNX export); at most 4 (enough to name them)."""
    found: list[str] = []
    for here, dirs, files in os.walk(root):
        rel = Path(here).relative_to(root)
        for d in list(dirs):
            sub = (rel / d).as_posix()
            kind = (own_folders or {}).get(sub)
            if (kind is not None and kind.recognise(root / sub) is None) or sub == HF_DOWNLOAD_CACHE:
                dirs.remove(d)
            elif (root / sub).is_symlink():
                found.append(sub + "/")
        found += [(rel / f).as_posix() for f in sorted(files) if (rel / f).as_posix() not in known]
        if len(found) > 3:
            break
    return found


# `hf download REPO --local-dir DIR` of a pushed bundle: its own metadata folder, the card and signature.
HF_DOWNLOAD_CACHE = ".cache/huggingface"
CARD_FILE = "README.md"
CARD_MARK = b"library_name: prop-keys"  # in the card `prop push` writes (deploy.publish.model_card)


def _file_names(listed: object) -> list[str]:
    return [str(n) for n in listed] if isinstance(listed, dict | list) else []


def _record_files(records: object) -> list[str]:
    if not isinstance(records, list):
        return []
    return [str(r["file"]) for r in records if isinstance(r, dict) and "file" in r]


def _own_folder(
    path: Path, name: str, meta_file: str, listed: Callable[[dict, Path], set[str] | None],
    own_folders: dict[str, OutputKind] | None = None,
) -> str | None:  # fmt: skip
    """A folder prop wrote: empty, or its ``meta_file`` is prop's (``listed(meta, folder)``: the other
    files it names; None: not prop's) and nothing else is in it."""
    if not path.is_dir():
        return _not_a(path, name)
    if not _entries(path):
        return None
    meta = _read_json(path / meta_file)
    known = listed(meta, path) if isinstance(meta, dict) else None
    if known is None:
        return _not_a(path, name)
    extra = _unlisted(path, {meta_file, *known}, own_folders)
    return f"{name} that also holds files prop did not write ({_names(extra)})" if extra else None


def _bundle_files(m: dict, folder: Path) -> set[str] | None:
    if not (isinstance(m.get(C.M_FORMAT), int) and C.M_PROP_VERSION in m):
        return None
    known = {C.SIGNATURE_FILE, *_file_names(m.get(C.M_FILES)), *_record_files(m.get(C.M_RECORDS))}
    return known | ({CARD_FILE} if CARD_MARK in _head(folder / CARD_FILE, 4096) else set())


def _export_files(meta: dict, folder: Path) -> set[str] | None:
    if not (isinstance(meta.get("format"), int) and "graphs" in meta):
        return None
    public = meta.get("sealed")  # a sealed bundle's export: its records' public part, with their files
    records = _record_files(public.get(C.M_RECORDS)) if isinstance(public, dict) else []
    return {*_file_names(meta["graphs"]), *records}


def _is_bundle(path: Path) -> str | None:
    return _own_folder(path, "a prop bundle", C.MANIFEST, _bundle_files, {C.EXPORT_DIR: EXPORT})


def _is_export(path: Path) -> str | None:
    return _own_folder(path, "a prop ONNX export", C.EXPORT_META, _export_files)


def _is_peft(path: Path) -> str | None:
    if not path.is_dir():
        return _not_a(path, "a peft adapter folder")
    config = _read_json(path / C.PEFT_CONFIG)
    lora = isinstance(config, dict) and config.get("peft_type") == "LORA"
    if not _entries(path) or (lora and set(_entries(path)) <= {C.PEFT_CONFIG, C.PEFT_WEIGHTS}):
        return None
    return _not_a(path, "a peft LoRA adapter folder as prop export --peft writes")


def _head(path: Path, n: int) -> bytes:
    try:
        with open(path, "rb") as f:
            return f.read(n)
    except OSError:
        return b""


def _is_array(path: Path) -> str | None:
    if path.is_file() and _head(path, 6) == b"\x93NUMPY":
        return None
    return _not_a(path, "a .npy array")


def _is_key(path: Path) -> str | None:
    if not path.is_file():
        return _not_a(path, "a key file")
    st = path.stat()
    if not C.KEY_BITS_MIN // 8 <= st.st_size <= C.KEY_BITS_MAX // 8:
        return f"a file of {st.st_size} bytes, not a key file"
    if os.name == "posix" and st.st_mode & 0o077:  # keygen writes 0600; a small file others read is not one
        return f"a file others may read (mode {stat.S_IMODE(st.st_mode):04o}), not a key file"
    return None


def _is_audit_report(path: Path) -> str | None:
    report = _read_json(path) if path.is_file() else None
    if isinstance(report, dict) and str(report.get("schema", "")).startswith("prop-audit/"):
        return None
    return _not_a(path, "a prop audit report")


def _is_plot(path: Path) -> str | None:
    head = _head(path, 4096) if path.is_file() else b""
    if head.startswith(b"\x89PNG\r\n\x1a\n") and b"Matplotlib" in head:
        return None
    return _not_a(path, "a PNG plot")


BUNDLE = OutputKind("a prop bundle (a folder of prop's manifest.json and its files)", True, _is_bundle)
EXPORT = OutputKind("a prop ONNX export (a folder of prop's export.json and its graphs)", True, _is_export)
PEFT = OutputKind("a peft LoRA adapter folder (adapter_config.json and its weights only)", True, _is_peft)
ARRAY = OutputKind("a .npy array file", False, _is_array)
KEY = OutputKind(
    f"a key file as prop keygen writes ({C.KEY_BITS_MIN // 8} to {C.KEY_BITS_MAX // 8} bytes, mode 0600)",
    False,
    _is_key,
)
AUDIT_REPORT = OutputKind("a prop audit report (JSON)", False, _is_audit_report)
PLOT = OutputKind("a PNG plot drawn by matplotlib", False, _is_plot)


def check_replaceable(out: Path, kind: OutputKind, flag: str) -> bool:
    """Whether something is at ``out``; if it is not prop's own output of ``kind``, refuse, --force or
    not: prop never replaces what it did not write."""
    out = Path(out)
    if not (out.exists() or out.is_symlink()):
        return False
    try:
        there = kind.recognise(out)
    except OSError as e:  # a folder that cannot be listed, a file that cannot be read: not provably ours
        there = f"something prop cannot read ({e.strerror or type(e).__name__})"
    if there is not None:
        raise PropError(
            f"{flag} {out} is {there}",
            f"choose another {flag}, or move it away yourself: --force replaces only {kind.replaces}",
        )
    return True


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


# ---- Nothing through a link ---------------------------------------------------------------------
# A bundle is a folder of plain files; a symbolic link in it would make prop read, write or delete
# outside it (issue 31: `users/` linked elsewhere, add-user wrote its record there and remove-user
# deleted a file there). Links are refused when a bundle is read (bundle.read.check_tree), and checked
# again right before each write or delete inside one: the folder may change while a command runs
# (add-user trains for minutes between its read and its write).

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
