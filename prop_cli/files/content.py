"""The bytes of prop's own files: the one JSON style, and a file's sha256 (what manifests record)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def dump_json(obj: dict) -> str:
    """The one JSON style of prop's files: sorted keys, indented, newline-terminated."""
    return json.dumps(obj, sort_keys=True, indent=2) + "\n"
