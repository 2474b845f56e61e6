from __future__ import annotations

from pathlib import Path

import typer

from .common import err, out, print_json


def push(
    bundle: Path = typer.Argument(..., help="Bundle directory written by prop personalize."),
    repo: str = typer.Argument(..., help="Hub model repo, <org or user>/<name> (created if missing)."),
    private: bool = typer.Option(False, "--private", help="Create the repo as private."),
    revision: str = typer.Option(None, "--revision", help="Branch to push to (created if missing)."),
    onnx_dir: Path = typer.Option(
        None, "--onnx-dir", help="ONNX export to include (default: BUNDLE/onnx if it exists)."
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON."),
) -> None:
    """Upload a bundle (and its ONNX export) to the Hugging Face hub with a generated model card."""
    from prop_cli.hub import push_bundle

    err.print(f"uploading {bundle} to {repo} ...")
    result = push_bundle(bundle, repo, private=private, revision=revision, onnx_dir=onnx_dir)
    if as_json:
        print_json(
            {"repo": result.repo_id, "url": result.url, "files": result.files, "revision": result.revision}
        )
        return
    out.print(
        f"pushed {len(result.files)} files to {result.url}"
        + (f" ({result.revision})" if result.revision else "")
    )
