from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from prop_cli.constants import KEY_BITS_DEFAULT, KEY_BITS_MAX, KEY_BITS_MIN

from .common import err, print_json
from .options import Force, Json


def keygen(
    path: Annotated[Path, typer.Argument(metavar="PATH", help="Key file to create (mode 0600).")],
    bits: Annotated[
        int, typer.Option("--bits", help=f"Key size: a multiple of 8 from {KEY_BITS_MIN} to {KEY_BITS_MAX}.")
    ] = KEY_BITS_DEFAULT,
    force: Force = False,
    as_json: Json = False,
) -> None:
    """Write a new random key (from the OS) to PATH, readable by you only."""
    from prop_cli.api import generate_key_file

    generate_key_file(path, bits=bits, force=force)
    if as_json:
        print_json({"path": str(path), "bits": bits, "mode": "0600"})
    err.print(f"wrote a {bits}-bit key to {path} (mode 0600); keep it secret, keep a backup")
