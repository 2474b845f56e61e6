from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from prop_cli.config import ExportSettings
from prop_cli.constants import DEFAULT_THREADS
from prop_cli.errors import plural

from .common import err, fail, out, print_json, read_passphrase
from .options import (
    AllowRollback,
    AllowUnenrolledKey,
    BundleArch,
    BundleArg,
    Force,
    Json,
    Passphrase,
    Threads,
    TrustRemoteCode,
    config_options,
    opt,
)

SETTINGS = {  # ExportSettings field -> help of its --flag
    "opset": f"ONNX opset version ({ExportSettings.MIN_OPSET}..{ExportSettings.MAX_OPSET}).",
    "atol": "Largest accepted |onnxruntime - torch| difference in the check.",
}
Onnx = Annotated[bool, opt("--onnx", "Export ONNX graphs (needs: pip install 'prop-keys[onnx]').")]
OutDir = Annotated[Path | None, opt("--out", "Folder to write the graphs to (default: BUNDLE/onnx).")]
PeftDir = Annotated[
    Path | None,
    opt("--peft", "New folder: the payload your key opens in a sealed bundle (--payload peft-lora) as a "
                  "standard peft LoRA adapter. It is your behaviour in the clear."),
]  # fmt: skip
LeRobotDir = Annotated[
    Path | None,
    opt("--lerobot", "New folder: a LeRobot policy folder naming the bundle, for --policy.path in "
                     "LeRobot's tools (lerobot-rollout ...; plugin lerobot_policy_prop). No weights or key."),
]  # fmt: skip
ResizeImages = Annotated[
    bool, opt("--resize-images", "With --lerobot: resize camera frames of another size to the bundle's.")
]
VerifyKey = Annotated[
    Path | None,
    opt("--key-file", "Verify with your key and bind it to the graphs (prop run --onnx runs bound keys)."),
]
VerifyInputs = Annotated[Path | None, opt("--input", "Verify on these inputs (.npy or a data file's x).")]


@config_options(ExportSettings, SETTINGS, into="settings")
def export(
    bundle: BundleArg, settings: ExportSettings, onnx: Onnx = False, out_dir: OutDir = None,
    peft: PeftDir = None, lerobot: LeRobotDir = None, resize_images: ResizeImages = False,
    key_file: VerifyKey = None, passphrase: Passphrase = False, input_path: VerifyInputs = None,
    threads: Threads = DEFAULT_THREADS, force: Force = False, as_json: Json = False,
    trust_remote_code: TrustRemoteCode = False, arch: BundleArch = None,
    allow_unenrolled_key: AllowUnenrolledKey = False,
    allow_rollback: AllowRollback = False,
) -> None:  # fmt: skip
    """Export a bundle to ONNX (base, keyed, encoder + policy graphs), verified with onnxruntime; a
    sealed user's payload as a peft LoRA adapter (--peft DIR); or a LeRobot policy folder (--lerobot DIR)."""
    if sum((onnx, peft is not None, lerobot is not None)) != 1:
        fail("choose one export format", "pass --onnx, --peft DIR or --lerobot DIR")
    if resize_images and lerobot is None:
        fail("--resize-images goes with --lerobot", "drop it, or export with --lerobot DIR")
    if lerobot is not None:
        from prop_cli.api import export_lerobot_folder

        written = export_lerobot_folder(
            bundle, lerobot, resize_images=resize_images, force=force, trust_remote_code=trust_remote_code,
            allow_rollback=allow_rollback,
        )  # fmt: skip
        if as_json:
            print_json({"out": str(written), "bundle": str(bundle)})
        else:
            out.print(f"wrote {written} (run it with lerobot-rollout --policy.path={written} "
                      "--policy.key_file=YOUR.key ...)")  # fmt: skip
        return
    if peft is not None:
        _export_peft(
            bundle, peft, key_file, passphrase, force, as_json, trust_remote_code, arch, allow_rollback
        )
        return
    from prop_cli.api import export_bundle

    result = export_bundle(
        bundle, out_dir, settings, key_file=key_file,
        passphrase=read_passphrase() if passphrase else None, input_path=input_path, force=force,
        threads=threads, trust_remote_code=trust_remote_code, arch=arch,
        allow_unenrolled_key=allow_unenrolled_key, allow_rollback=allow_rollback,
    )  # fmt: skip
    if as_json:
        print_json({"out": str(result.out), "ok": result.ok, "opset": result.opset, "atol": result.atol,
                    "files": result.files, "verification": result.table})  # fmt: skip
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


def _export_peft(bundle, peft, key_file, passphrase, force, as_json, trust_remote_code, arch,
                 allow_rollback) -> None:  # fmt: skip
    from prop_cli.api import export_peft_adapter

    result = export_peft_adapter(
        bundle, peft, key_file=key_file, passphrase=read_passphrase() if passphrase else None, force=force,
        trust_remote_code=trust_remote_code, arch=arch, allow_rollback=allow_rollback,
    )  # fmt: skip
    err.print(f"prop: note: {result.out} holds your behaviour unencrypted: keep it as you keep your key")
    if as_json:
        print_json({"out": str(result.out), "layers": result.layers, "rank": result.rank,
                    "base": result.base})  # fmt: skip
    else:
        out.print(f"wrote {result.out} (peft LoRA adapter: {plural(result.layers, 'layer')}, "
                  f"rank {result.rank}; base {result.base})")  # fmt: skip


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
