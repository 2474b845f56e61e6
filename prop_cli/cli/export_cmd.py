from __future__ import annotations

from pathlib import Path

import typer

from .common import err, fail, key_for_bundle, out, print_json


def export(
    bundle: Path = typer.Argument(..., help="Bundle directory written by prop personalize."),
    onnx: bool = typer.Option(False, "--onnx", help="Export ONNX graphs (the only format so far)."),
    out_dir: Path = typer.Option(None, "--out", help="Folder to write the graphs to (default: BUNDLE/onnx)."),
    opset: int = typer.Option(18, "--opset", help="ONNX opset version (13..20)."),
    atol: float = typer.Option(
        1e-5, "--atol", help="Largest accepted |onnxruntime - torch| difference in the verification."
    ),
    key_file: Path = typer.Option(
        None, "--key-file", help="Also verify with your key (the key is never written to the graphs)."
    ),
    passphrase: bool = typer.Option(False, "--passphrase", help="Verify with your passphrase's key."),
    input_path: Path = typer.Option(
        None, "--input", help="Verify on these inputs (.npy or .npz with x) instead of random ones."
    ),
    force: bool = typer.Option(False, "--force", help="Replace an existing --out folder."),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON."),
) -> None:
    """Export a bundle to ONNX (base, keyed, encoder + policy graphs), verified with onnxruntime."""
    if not onnx:
        fail("choose an export format", "pass --onnx")
    from prop_cli.api import load_inputs
    from prop_cli.bundle import load_bundle
    from prop_cli.export import export_onnx, require_onnx

    require_onnx()
    b = load_bundle(bundle)
    key = key_for_bundle(key_file, passphrase, b.manifest)
    x = load_inputs(input_path, b) if input_path is not None else None
    result = export_onnx(b, out_dir, opset=opset, atol=atol, key=key, inputs=x, force=force)
    if as_json:
        print_json(
            {
                "out": str(result.out),
                "ok": result.ok,
                "opset": result.opset,
                "atol": result.atol,
                "files": result.files,
                "verification": result.table,
            }
        )
    else:
        _print_table(result)
    if not result.ok:
        err.print(
            f"prop: verification failed: a difference is above --atol {result.atol:g}; nothing was written"
            " (raise --atol if that precision is acceptable)"
        )
        raise typer.Exit(1)
    if not as_json:
        out.print(f"wrote {result.out} ({', '.join(result.files)})")


def _print_table(result) -> None:
    from rich.table import Table

    table = Table(title=f"onnxruntime vs torch (opset {result.opset}, atol {result.atol:g})")
    for col in ("graph", "key", "max abs diff", "max rel diff", "ok"):
        table.add_column(col)
    for r in result.table:
        table.add_row(
            r["graph"], r["key"], f"{r['max_abs']:.2e}", f"{r['max_rel']:.2e}", "yes" if r["ok"] else "NO"
        )
    out.print(table)
