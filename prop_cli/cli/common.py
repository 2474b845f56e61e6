"""What the commands share: output streams, key input, JSON output. No torch here (fast --help)."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import typer
from rich.console import Console

out = Console()  # results
err = Console(stderr=True)  # progress and diagnostics

DEBUG_HINT = "set PROP_DEBUG=1 for a traceback"


def fail(what: str, fix: str | None = None):
    """Raise the one expected-failure type from CLI code."""
    from prop_cli.errors import PropError

    raise PropError(what, fix)


def parse_json_option(value: str | None, flag: str) -> dict | None:
    if value is None:
        return None
    try:
        parsed = json.loads(value)
    except json.JSONDecodeError as e:
        fail(f"{flag} is not valid JSON ({e.msg})", f"e.g. {flag} '{{\"hidden\": 256}}'")
    if not isinstance(parsed, dict):
        fail(f"{flag} must be a JSON object", f"e.g. {flag} '{{\"hidden\": 256}}'")
    return parsed


def read_passphrase(prompt: str) -> str:
    from prop_cli.constants import ENV_PASSPHRASE

    value = os.environ.get(ENV_PASSPHRASE)
    if value is None:
        if not sys.stdin.isatty():
            fail(
                "--passphrase needs a terminal to prompt on",
                f"set {ENV_PASSPHRASE} for scripts, or use --key-file",
            )
        value = typer.prompt(prompt, hide_input=True)
    return value


def print_json(obj: dict) -> None:
    from prop_cli.bundle import dump_json

    sys.stdout.write(dump_json(obj))


def key_for_bundle(key_file: Path | None, passphrase: bool, manifest: dict):
    """The key bits for an existing bundle, from a key file or its passphrase (salt in the manifest)."""
    from prop_cli import constants as C
    from prop_cli.keys import passphrase_bits, read_key_file

    bits = int(manifest[C.M_KEY]["bits"])
    if key_file is not None and passphrase:
        fail("--key-file and --passphrase both given", "use one of them")
    if key_file is not None:
        return read_key_file(key_file, bits)
    if passphrase:
        kdf = manifest[C.M_KEY].get("kdf")
        if not kdf:
            fail("this bundle was not made with a passphrase", "use --key-file")
        return passphrase_bits(read_passphrase("Passphrase"), bytes.fromhex(kdf["salt"]), bits)
    return None
