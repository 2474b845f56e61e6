"""`prop run`: the outputs of a bundle for a file of inputs, with or without a key, in torch or through its
ONNX export, written to a .npy file (never half-written, never over what is not one without --force)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from prop_cli.bundle import load_bundle
from prop_cli.core.key_files import key_for_bundle
from prop_cli.files import ARRAY, check_not_input, check_output, write_file
from prop_cli.threads import check as check_threads
from prop_cli.threads import configure as configure_threads

from .policy import require_enrolled, run_inputs, seed_noise


@dataclass
class RunResult:
    output: Path
    shape: tuple[int, ...]
    keyed: bool
    onnx: bool


def run_file(
    bundle_path: Path,
    input_path: Path,
    output: Path,
    *,
    key_file: Path | None = None,
    passphrase: str | None = None,
    onnx: bool = False,
    onnx_dir: Path | None = None,
    force: bool = False,
    threads: int | None = None,
    trust_remote_code: bool = False,
    noise_seed: int = 0,
    arch: str | None = None,
    allow_unenrolled_key: bool = False,
    allow_rollback: bool = False,
) -> RunResult:
    """`prop run`: outputs for the inputs in a file, written to ``output`` (.npy), with or without a key.
    With a key, only what its holder enrolled runs (``bundle.enrol``): a key enrolled in nothing is
    refused (``allow_unenrolled_key``: the bundle's base runs, with a warning), and so is a bundle
    changed since the key was enrolled, and a copy older than one this machine has seen (unless
    ``allow_rollback``).
    ``noise_seed``: where a policy samples its chunks (LeRobot Diffusion), the seed of their noise."""
    check_threads(threads)
    check_not_input(output, "--output", [bundle_path, input_path, key_file, onnx_dir])
    check_output(output, force, what="output", flag="--output", kind=ARRAY)
    bundle = load_bundle(
        bundle_path, trust_remote_code=trust_remote_code, arch=arch, allow_rollback=allow_rollback
    )
    seed_noise(bundle.loaded, noise_seed)
    n_threads = configure_threads(bundle.parameters, threads)
    key = key_for_bundle(bundle.manifest, key_file, passphrase)
    # Before any input is read: a key enrolled in nothing is refused unless allowed (the run warns).
    keyed = key is not None and require_enrolled(bundle, key, allow_unenrolled_key)
    use_onnx = onnx or onnx_dir is not None
    runner = None
    if use_onnx:

        def runner(x: np.ndarray) -> np.ndarray:
            from .onnx import run_onnx

            return run_onnx(
                bundle, x, key, onnx_dir, threads=n_threads, allow_unenrolled=allow_unenrolled_key
            )

    y = run_inputs(bundle, input_path, key, allow_unenrolled=allow_unenrolled_key, onnx=runner)

    def save(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            np.save(f, y)

    write_file(output, save, what="output", flag="--output")
    return RunResult(Path(output), tuple(y.shape), keyed, use_onnx)
