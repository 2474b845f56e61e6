from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from prop_cli.constants import DEFAULT_THREADS

from .common import err, print_json, read_passphrase
from .options import (
    AllowRollback,
    AllowUnenrolledKey,
    BundleArch,
    BundleArg,
    Force,
    Inputs,
    Json,
    KeyFile,
    OnnxDir,
    Passphrase,
    Threads,
    TrustRemoteCode,
)


def run(
    bundle: BundleArg,
    input_path: Inputs,
    output: Annotated[Path, typer.Option("--output", help="Where to write the outputs (.npy).")],
    key_file: KeyFile = None,
    passphrase: Passphrase = False,
    force: Force = False,
    onnx: Annotated[
        bool,
        typer.Option("--onnx", help="Run the exported ONNX graphs with onnxruntime (prop export --onnx)."),
    ] = False,
    onnx_dir: OnnxDir = None,
    threads: Threads = DEFAULT_THREADS,
    noise_seed: Annotated[
        int,
        typer.Option("--noise-seed", min=0, help="Seed of a sampling policy's noise (LeRobot Diffusion): "
                     "each frame's chunk is LeRobot's after torch.manual_seed(N)."),
    ] = 0,
    as_json: Json = False,
    trust_remote_code: TrustRemoteCode = False,
    arch: BundleArch = None,
    allow_unenrolled_key: AllowUnenrolledKey = False,
    allow_rollback: AllowRollback = False,
) -> None:
    """Run a bundle on inputs: with your key your behaviour, without a key the original's."""
    from prop_cli.api import run_file

    result = run_file(
        bundle, input_path, output, key_file=key_file, passphrase=read_passphrase() if passphrase else None,
        onnx=onnx, onnx_dir=onnx_dir, force=force, threads=threads, trust_remote_code=trust_remote_code,
        noise_seed=noise_seed, arch=arch, allow_unenrolled_key=allow_unenrolled_key,
        allow_rollback=allow_rollback,
    )  # fmt: skip
    if as_json:
        print_json({"output": str(result.output), "shape": list(result.shape), "keyed": result.keyed,
                    "onnx": result.onnx})  # fmt: skip
    given = key_file is not None or passphrase
    base = "the bundle's base: the key is enrolled in nothing in it"
    how = "keyed" if result.keyed else (base if given else "no key")
    err.print(f"wrote {result.output} {result.shape} ({how})")
