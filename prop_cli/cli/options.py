"""Options the commands share, declared once (typer ``Annotated`` aliases). No torch here.

Defaults are not written here: each command takes them from the settings dataclasses in
``prop_cli.config`` (or ``prop_cli.constants``), so a default lives in exactly one place.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import typing
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any

import typer

FORMATS = "`prop formats` lists the formats"


def opt(flag: str, help: str, **kwargs):
    """``typer.Option(flag, help=help)``: commands declare their own options as one-line aliases."""
    return typer.Option(flag, help=help, **kwargs)


Checkpoint = Annotated[
    str,
    typer.Argument(
        metavar="CHECKPOINT", help=f"Checkpoint file or folder, or hf://org/name[@rev]/path ({FORMATS})."
    ),
]


def bundle_folder(value: Path) -> Path:
    """A bundle's manifest.json names its bundle: ``mine.prop/manifest.json`` is read as ``mine.prop``
    (only that file name, and only where it is a file: anything else is checked as given)."""
    from prop_cli.constants import MANIFEST

    path = Path(value)
    return path.parent if path.name == MANIFEST and path.is_file() else path


BundleArg = Annotated[
    Path,
    typer.Argument(
        metavar="BUNDLE", help="Bundle directory written by prop personalize (or its manifest.json).",
        callback=bundle_folder,
    ),
]  # fmt: skip

Arch = Annotated[str | None, typer.Option("--arch", help="Your module: package.module:factory.")]
BundleArch = Annotated[
    str | None,
    typer.Option(
        "--arch",
        help="A bundle of your own module: its factory named from here (file.py:factory or "
        "package.module:factory), called instead of the one the bundle records; your code, so no "
        "--trust-remote-code.",
    ),
]
ArchKwargs = Annotated[str | None, typer.Option("--arch-kwargs", help="JSON keyword arguments for --arch.")]
Activation = Annotated[
    str | None,
    typer.Option(
        "--activation", help="Plain MLP state dicts: the activation (relu if the file does not say)."
    ),
]
Layers = Annotated[
    list[str] | None,
    typer.Option("--layers", help="Layers to key: exact name, dotted suffix, regex or all-linear; repeat."),
]
Exclude = Annotated[
    list[str] | None, typer.Option("--exclude", help="Layers not to key (same forms); repeat.")
]

KeyFile = Annotated[
    Path | None, typer.Option("--key-file", help="Your key file; without a key: the original behaviour.")
]
Passphrase = Annotated[
    bool,
    typer.Option("--passphrase", help="Derive the key from your passphrase (prompted, or PROP_PASSPHRASE)."),
]
Force = Annotated[bool, typer.Option("--force", help="Replace existing output files or folders.")]
AllowUnenrolledKey = Annotated[
    bool,
    typer.Option(
        "--allow-unenrolled-key",
        help="Run the bundle's base when the key is enrolled in nothing in it (by default that is an "
        "error: the bundle may have been replaced or the user removed); for scripts that test wrong keys.",
    ),
]
TrustRemoteCode = Annotated[
    bool,
    typer.Option(
        "--trust-remote-code",
        help="Import and run code the bundle's or checkpoint's files name (model.arch, an entry point, "
        "processor steps): only for files from someone you trust.",
    ),
]
AllowRollback = Annotated[
    bool,
    typer.Option(
        "--allow-rollback",
        help="Accept a copy of the bundle older than one this machine has seen (with a warning); without "
        "it, a key is refused there (docs/threat-model.md).",
    ),
]
WeakPassphrase = Annotated[
    bool, typer.Option("--weak-passphrase", help="Accept a passphrase that is quick to guess (not advised).")
]
Json = Annotated[bool, typer.Option("--json", help="Print the result as JSON (sorted, indented).")]
Device = Annotated[str, typer.Option("--device", help="auto, cpu or cuda[:N].")]
Threads = Annotated[
    int,
    typer.Option(
        "--threads",
        help="CPU threads for torch; 0 = one for small models, else the idle cores (OMP_NUM_THREADS if set).",
    ),
]
OnnxDir = Annotated[Path | None, typer.Option("--onnx-dir", help="The ONNX export (default: BUNDLE/onnx).")]
Inputs = Annotated[
    Path,
    typer.Option(
        "--input", help="Inputs: .npy (N, ...), a data file's x, or a LeRobotDataset root (policies)."
    ),
]


def config_options(cls: type, helps: dict[str, str], into: str = "config") -> Callable:
    """Give a command one ``--flag`` per field of the settings dataclass ``cls`` named in ``helps``
    (flag = the field name with dashes, default = the field's default); the command receives the
    settings as the keyword argument ``into`` instead of the separate values."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    settings = {name: (hints[name], fields[name].default, text) for name, text in helps.items()}
    return settings_options(settings, cls, into)


def settings_options(
    settings: dict[str, tuple[Any, Any, str]], build: Callable[..., Any], into: str = "config"
) -> Callable:
    """Give a command one ``--flag`` per setting (name -> (type, default, help), as
    ``prop_cli.config.cli_settings`` reads them from the settings fields; flag = the name with dashes);
    the command receives ``build(**values)`` as the keyword argument ``into`` instead of the values."""

    def decorate(fn: Callable) -> Callable:
        sig = inspect.signature(fn, eval_str=True)
        own = [p for p in sig.parameters.values() if p.name != into]
        added = [
            inspect.Parameter(
                name,
                inspect.Parameter.KEYWORD_ONLY,
                default=default,
                annotation=Annotated[kind, typer.Option("--" + name.replace("_", "-"), help=text)],
            )
            for name, (kind, default, text) in settings.items()
        ]

        @functools.wraps(fn)
        def command(*args, **kwargs):
            built = build(**{name: kwargs.pop(name) for name in settings})
            return fn(*args, **{into: built}, **kwargs)

        command.__signature__ = sig.replace(parameters=own + added)  # type: ignore[attr-defined]
        return command

    return decorate
