from __future__ import annotations

from pathlib import Path

import typer

from .common import err, key_for_bundle


def run(
    bundle: Path = typer.Argument(..., help="Bundle directory written by prop personalize."),
    input_path: Path = typer.Option(..., "--input", help="Inputs: .npy (N, ...) or .npz with x."),
    output: Path = typer.Option(..., "--output", help="Where to write the outputs (.npy)."),
    key_file: Path = typer.Option(
        None, "--key-file", help="Your key; without a key: the original behaviour."
    ),
    passphrase: bool = typer.Option(False, "--passphrase", help="Derive the key from your passphrase."),
    force: bool = typer.Option(False, "--force", help="Replace an existing --output."),
    onnx: bool = typer.Option(
        False, "--onnx", help="Run the exported ONNX graphs with onnxruntime (see prop export --onnx)."
    ),
    onnx_dir: Path = typer.Option(None, "--onnx-dir", help="The ONNX export to run (default: BUNDLE/onnx)."),
) -> None:
    """Run a bundle on inputs: with your key your behaviour, without a key the original's."""
    import numpy as np

    from prop_cli.api import load_inputs, run_bundle
    from prop_cli.bundle import check_output, load_bundle

    check_output(output, force, what="output")
    b = load_bundle(bundle)
    key = key_for_bundle(key_file, passphrase, b.manifest)
    x = load_inputs(input_path, b)
    if onnx or onnx_dir is not None:
        from prop_cli.export import run_onnx

        y = run_onnx(b, x, key, onnx_dir)
    else:
        y = run_bundle(b, x, key)
    tmp = output.with_name(output.name + ".tmp.npy")
    np.save(tmp, y)
    tmp.replace(output)
    err.print(f"wrote {output} {tuple(y.shape)} ({'keyed' if key is not None else 'no key'})")
