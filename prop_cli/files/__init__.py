"""What prop writes and reads on the user's disk, by job: ``atomic`` (never half a file; the outputs put in
place so far), ``kinds`` (each kind of output recognised: what --force may replace), ``outputs`` (where a
command may write), ``links`` (nothing through a symbolic link), ``lock`` (one writer of a bundle at a
time), ``descriptors`` (folders by descriptor: the walk below one with no link followed, and reads that
way) and ``content`` (the JSON style, sha256).
Import from here: this is the one surface the rest of prop uses."""

from .atomic import (
    check_writable,
    replace_dir,
    staged_dir,
    uninterrupted,
    write_file,
    write_text,
    written,
    wrote,
)
from .content import dump_json, sha256_file
from .descriptors import held, held_at, opened, read, sha256_inside
from .kinds import (
    ARRAY,
    AUDIT_REPORT,
    BUNDLE,
    CARD_FILE,
    CARD_MARK,
    EXPORT,
    HF_DOWNLOAD_CACHE,
    KEY,
    LEROBOT_FOLDER,
    PEFT,
    PLOT,
    OutputKind,
    check_replaceable,
)
from .links import RESTORE, TAMPERED, link_error, no_links, remove_inside, shown, write_inside
from .lock import bundle_lock, delete, put, remove_at, write_at
from .outputs import check_not_input, check_output

__all__ = [
    "ARRAY",
    "AUDIT_REPORT",
    "BUNDLE",
    "CARD_FILE",
    "CARD_MARK",
    "EXPORT",
    "HF_DOWNLOAD_CACHE",
    "KEY",
    "LEROBOT_FOLDER",
    "PEFT",
    "PLOT",
    "RESTORE",
    "TAMPERED",
    "OutputKind",
    "check_not_input",
    "check_output",
    "check_replaceable",
    "bundle_lock",
    "check_writable",
    "delete",
    "dump_json",
    "held",
    "held_at",
    "link_error",
    "no_links",
    "opened",
    "put",
    "read",
    "remove_at",
    "remove_inside",
    "replace_dir",
    "sha256_file",
    "sha256_inside",
    "shown",
    "staged_dir",
    "uninterrupted",
    "write_at",
    "write_file",
    "write_inside",
    "write_text",
    "written",
    "wrote",
]
