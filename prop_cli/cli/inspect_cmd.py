from __future__ import annotations

from pathlib import Path

from .common import checkpoint_options, out, print_json
from .options import Activation, Arch, ArchKwargs, Checkpoint, Exclude, Json, Layers, TrustRemoteCode


def inspect(
    checkpoint: Checkpoint, arch: Arch = None, arch_kwargs: ArchKwargs = None, activation: Activation = None,
    layers: Layers = None, exclude: Exclude = None, as_json: Json = False,
    trust_remote_code: TrustRemoteCode = False,
) -> None:  # fmt: skip
    """List the linear layers and convolutions of a checkpoint, which ones would be keyed (and their share of
    the parameters), and what prop knows of it."""
    from rich.table import Table

    from prop_cli.api import inspect_checkpoint

    opts = checkpoint_options(arch, arch_kwargs, activation, trust_remote_code)
    info = inspect_checkpoint(checkpoint, opts, layers, exclude)
    if as_json:
        print_json(info)
        return
    model = info["model"]
    known = ", ".join(f"{k} {v}" for k, v in model.items() if k != "adapter" and v is not None)
    keyed = f"{info['keyed_parameters']:,} keyed ({100 * info['keyed_share']:.1f}%)"
    size = f"{info['parameters']:,} parameters, {keyed}"
    table = Table(
        title=f"{Path(checkpoint).name}: {info['adapter']} adapter, {size}" + (f"\n{known}" if known else ""),
        title_justify="left",
    )
    for col in ("layer", "kind", "in", "out", "parameters", "keyed"):
        table.add_column(col)
    for layer in info["layers"]:
        table.add_row(
            layer["name"],
            layer["kind"],
            str(layer["in_features"]),
            str(layer["out_features"]),
            f"{layer['parameters']:,}",
            "yes" if layer["keyed"] else "",
        )
    out.print(table)
