from __future__ import annotations

from pathlib import Path

import typer

from .common import out, parse_json_option, print_json


def inspect(
    checkpoint: str = typer.Argument(
        ..., help="Checkpoint: .safetensors, .pt/.pth, SB3 .zip, model folder, or hf://org/name/file."
    ),
    arch: str = typer.Option(None, "--arch", help="Your module: package.module:factory."),
    arch_kwargs: str = typer.Option(None, "--arch-kwargs", help="JSON keyword arguments for --arch."),
    activation: str = typer.Option(None, "--activation", help="Plain MLP activation (default relu)."),
    layers: list[str] = typer.Option(
        None, "--layers", help="Layers to key: name, dotted suffix, regex, all-linear."
    ),
    exclude: list[str] = typer.Option(None, "--exclude", help="Layers not to key (same forms)."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
) -> None:
    """List the linear layers of a checkpoint and which ones would be keyed."""
    from rich.table import Table

    from prop_cli.api import CheckpointOptions, inspect_checkpoint

    opts = CheckpointOptions(arch, parse_json_option(arch_kwargs, "--arch-kwargs"), activation)
    info = inspect_checkpoint(checkpoint, opts, layers or None, exclude or None)
    if as_json:
        print_json(info)
        return
    table = Table(
        title=f"{Path(checkpoint).name}: {info['adapter']} adapter, {info['parameters']:,} parameters"
    )
    for col in ("layer", "in", "out", "keyed"):
        table.add_column(col)
    for layer in info["layers"]:
        table.add_row(
            layer["name"],
            str(layer["in_features"]),
            str(layer["out_features"]),
            "yes" if layer["keyed"] else "",
        )
    out.print(table)
