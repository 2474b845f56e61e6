from __future__ import annotations

from .common import out, print_json
from .options import Json


def formats(as_json: Json = False) -> None:
    """List the checkpoint and data formats prop reads (from the adapter and data-source registries)."""
    from prop_cli.api import formats as registry

    info = registry()
    if as_json:
        print_json(info)
        return
    for title, key in (
        ("checkpoints (CHECKPOINT)", "checkpoints"),
        ("data (--data, --general-data)", "data"),
    ):
        out.print(f"{title}:", highlight=False)
        for f in info[key]:
            out.print(f"  {f['name']:8s} {f['summary']}", highlight=False)
