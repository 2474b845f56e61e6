from __future__ import annotations

from typing import Annotated

import typer

from .common import out, print_json
from .options import Json

Markdown = Annotated[bool, typer.Option("--markdown", help="Print the table docs/formats.md holds.")]


def formats(as_json: Json = False, markdown: Markdown = False) -> None:
    """List the checkpoint and data formats prop reads (from the adapter and data-source registries)."""
    from prop_cli.api import formats as registry

    info = registry()
    if as_json:
        print_json(info)
        return
    if markdown:
        print(formats_markdown(info))
        return
    sections = (("checkpoints (CHECKPOINT)", "checkpoints"), ("data (--data, --general-data)", "data"))
    for title, key in sections:
        out.print(f"{title}:", highlight=False)
        for f in info[key]:
            out.print(f"  {f['name']:8s} {f['summary']}", highlight=False)


def formats_markdown(info: dict) -> str:
    rows = [f"| checkpoint | `{f['name']}` | {f['summary']} |" for f in info["checkpoints"]]
    rows += [f"| data | `{f['name']}` | {f['summary']} |" for f in info["data"]]
    return "\n".join(["| for | name | what |", "| --- | --- | --- |", *rows])
