from __future__ import annotations

from pathlib import Path

import typer

from .common import err


def keygen(
    path: Path = typer.Argument(..., help="Key file to create (mode 0600)."),
    bits: int = typer.Option(128, "--bits", help="Key size: a multiple of 8 from 32 to 1024."),
    force: bool = typer.Option(False, "--force", help="Replace an existing file (its key is lost)."),
) -> None:
    """Write a new random key (from the OS) to PATH, readable by you only."""
    from prop_cli.keys import generate_key_file

    generate_key_file(path, bits=bits, force=force)
    err.print(f"wrote a {bits}-bit key to {path} (mode 0600); keep it secret, keep a backup")
