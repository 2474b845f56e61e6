"""Each kind of output prop writes, recognised at a path: what --force may replace (``check_replaceable``)."""

from __future__ import annotations

import json
import os
import stat
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from prop_cli import constants as C
from prop_cli.errors import PropError

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
    known = {C.SIGNATURE_FILE, C.BUNDLE_LOCK, *_file_names(m.get(C.M_FILES))}
    known |= set(_record_files(m.get(C.M_RECORDS)))
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


def _is_lerobot_folder(path: Path) -> str | None:
    if not path.is_dir():
        return _not_a(path, "a LeRobot policy folder")
    config = _read_json(path / C.LEROBOT_CONFIG)
    names = {C.LEROBOT_CONFIG, C.LEROBOT_PRE, C.LEROBOT_POST}
    ours = isinstance(config, dict) and config.get("type") == C.LEROBOT_POLICY_TYPE
    if not _entries(path) or (ours and set(_entries(path)) <= names):
        return None
    return _not_a(path, "a LeRobot policy folder as prop export --lerobot writes")


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
LEROBOT_FOLDER = OutputKind(
    "a LeRobot policy folder naming a prop bundle (config.json of type prop and two processor files)", True,
    _is_lerobot_folder,
)
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
