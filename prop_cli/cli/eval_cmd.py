from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from prop_cli.config import EvalSettings

from .common import err, out, print_json, read_passphrase
from .options import BundleArg, Json, KeyFile, Passphrase, config_options

SETTINGS = {
    "episodes": "Episodes for the user key, no key and --original.",
    "random_keys": "Random keys to roll out.",
    "neighbours": "One-bit neighbours of your key to roll out (needs the key).",
    "episodes_per_key": "Episodes per random key and per neighbour.",
    "max_steps": "Stop an episode after this many steps (0: the environment's limit).",
    "ignore_terminated": "Keep acting after the environment says terminated (stop at its time limit).",
    "seed": "First evaluation seed (keep it away from the seeds your data was recorded with).",
}


@config_options(EvalSettings, SETTINGS, into="settings")
def eval_(
    bundle: BundleArg,
    settings: EvalSettings,
    env: Annotated[
        str,
        typer.Option(
            "--env", help="gymnasium id; package:Id imports the package first (panda_gym:PandaReach-v3)."
        ),
    ],
    key_file: KeyFile = None,
    passphrase: Passphrase = False,
    obs_map: Annotated[
        str | None,
        typer.Option(
            "--obs-map", help="Policy feature=observation key, comma-separated (dict observations)."
        ),
    ] = None,
    metric: Annotated[
        str | None,
        typer.Option("--metric", help="Your preference metric: package.module:function(trajectory)."),
    ] = None,
    original: Annotated[
        str | None, typer.Option("--original", help="Also roll out the original checkpoint (the control).")
    ] = None,
    vecnormalize: Annotated[
        Path | None,
        typer.Option(
            "--vecnormalize",
            help="SB3 VecNormalize.save() file: normalise observations as in training (read without "
            "running its code).",
        ),
    ] = None,
    video: Annotated[
        Path | None,
        typer.Option(
            "--video", help="New folder: one mp4 per condition, its first episode (prop-cli[video])."
        ),
    ] = None,
    as_json: Json = False,
) -> None:
    """Roll a bundle out in an environment: your key, no key, random keys and neighbours, side by side."""
    from prop_cli.api import eval_bundle

    report = eval_bundle(
        bundle, env, settings, key_file=key_file, passphrase=read_passphrase() if passphrase else None,
        obs_map=obs_map, metric=metric, original=original, progress=lambda label: err.print(f"eval: {label}"),
        vecnormalize=vecnormalize, video=video,
    )  # fmt: skip
    if as_json:
        print_json(report)
        return
    from rich.table import Table

    table = Table(title=f"{report['env']}, seeds from {report['seeds'][0]}")
    for col in ("keys", "episodes", "return", "success", "metric"):
        table.add_column(col)

    def cell(r: dict, field: str) -> str:
        return f"{r[field]['mean']:.3f} ± {r[field]['se']:.3f}" if field in r else "-"

    for name, r in report["conditions"].items():
        table.add_row(name, str(r["episodes"]), cell(r, "return"), cell(r, "success"), cell(r, "metric"))
    out.print(table)
    if "video" in report:
        err.print(f"wrote {len(report['video']['files'])} videos to {report['video']['folder']}")
