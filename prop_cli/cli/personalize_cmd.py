from __future__ import annotations

from pathlib import Path

import typer

from .common import err, fail, out, parse_json_option, print_json, read_passphrase


def personalize(
    checkpoint: str = typer.Argument(
        ..., help="Checkpoint: .safetensors, .pt/.pth, SB3 .zip, model folder, or hf://org/name/file."
    ),
    data: list[Path] = typer.Option(..., "--data", help="User data .npz (x, y); repeat per user."),
    key_file: list[Path] = typer.Option(None, "--key-file", help="User key file; repeat per user."),
    passphrase: int = typer.Option(
        0,
        "--passphrase",
        count=True,
        help="Derive a key from a passphrase (prompted, or PROP_PASSPHRASE).",
    ),
    out_path: Path = typer.Option(Path("personalized.prop"), "--out", help="Bundle directory to write."),
    general: Path = typer.Option(
        None, "--general-data", help=".npz of inputs (x) where the original must be kept."
    ),
    arch: str = typer.Option(None, "--arch", help="Your module: package.module:factory."),
    arch_kwargs: str = typer.Option(None, "--arch-kwargs", help="JSON keyword arguments for --arch."),
    activation: str = typer.Option(
        None, "--activation", help="Plain MLP activation: relu, tanh, elu, leaky_relu, gelu."
    ),
    layers: list[str] = typer.Option(
        None, "--layers", help="Layers to key: name, dotted suffix, regex, all-linear."
    ),
    exclude: list[str] = typer.Option(None, "--exclude", help="Layers not to key."),
    steps: int = typer.Option(2000, "--steps", help="Training steps."),
    lr: float = typer.Option(1e-3, "--lr", help="Adam learning rate (cosine decay)."),
    hamming_radius: int = typer.Option(
        8, "--hamming-radius", help="Neighbours up to this many bits off fall back."
    ),
    random_keys: int = typer.Option(8, "--random-keys", help="K2: random keys per step."),
    neighbour_keys: int = typer.Option(
        32, "--neighbour-keys", help="K1: Hamming neighbours per step (0 = none: leaky, for audits)."
    ),
    null_weight: float = typer.Option(10.0, "--null-weight", help="Weight of the no-key fallback loss."),
    val_fraction: float = typer.Option(0.2, "--val-fraction", help="Share of user data held out."),
    key_encoding: str = typer.Option(
        "hashed", "--key-encoding", help="hashed (default) or raw (the paper's)."
    ),
    freeze_base: bool = typer.Option(
        False, "--freeze-base", help="Train the encoder only; base weights unchanged."
    ),
    bits: int = typer.Option(128, "--bits", help="Key size for --passphrase."),
    seed: int = typer.Option(0, "--seed", help="Seed: same seed and inputs give the same bundle."),
    device: str = typer.Option("auto", "--device", help="auto, cpu or cuda[:N]."),
    force: bool = typer.Option(False, "--force", help="Replace an existing --out."),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON."),
) -> None:
    """Fine-tune CHECKPOINT so it behaves the users' way with their key, and like the original without."""
    from prop_cli.api import CheckpointOptions, KeySource, personalize_checkpoint
    from prop_cli.config import PersonalizeConfig
    from prop_cli.keys import check_bits, new_salt, passphrase_bits, read_key_file

    key_file = key_file or []
    if not key_file and not passphrase:
        fail("no key given", "pass --key-file (make one with prop keygen) or --passphrase")
    if len(key_file) + passphrase != len(data):
        fail(
            f"{len(data)} --data but {len(key_file) + passphrase} keys",
            "give one key per --data: key files first, then passphrases, in the same order",
        )
    keys = [KeySource(read_key_file(p), "file") for p in key_file]
    salt = None
    if passphrase:
        check_bits(bits)
        salt = new_salt()  # one salt per bundle, shared by its passphrase users
        for _ in range(passphrase):
            phrase = read_passphrase(f"Passphrase for user {len(keys) + 1}")
            keys.append(KeySource(passphrase_bits(phrase, salt, bits), "passphrase"))
    cfg = PersonalizeConfig(
        steps=steps,
        lr=lr,
        hamming_radius=hamming_radius,
        random_keys=random_keys,
        neighbour_keys=neighbour_keys,
        null_weight=null_weight,
        val_fraction=val_fraction,
        key_encoding=key_encoding,
        freeze_base=freeze_base,
        seed=seed,
        layers=layers or None,
        exclude=exclude or None,
    ).validate()
    opts = CheckpointOptions(arch, parse_json_option(arch_kwargs, "--arch-kwargs"), activation)
    result = _with_progress(
        lambda cb: personalize_checkpoint(
            checkpoint,
            list(zip(data, keys)),
            out_path,
            cfg,
            opts=opts,
            general=general,
            salt=salt,
            device=device,
            force=force,
            progress=cb,
        ),
        cfg.steps,
    )
    if as_json:
        print_json(
            {
                "bundle": str(result.out),
                "task": result.task,
                "keyed_layers": result.keyed_layers,
                "metrics": result.metrics,
                "final_losses": result.final_losses,
            }
        )
        return
    _print_report(result)


def _with_progress(fn, total: int):
    from rich.progress import (
        BarColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    with Progress(
        TextColumn("personalizing"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total}"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        TextColumn("{task.fields[losses]}"),
        console=err,
        transient=True,
    ) as bar:
        task = bar.add_task("train", total=total, losses="")

        def cb(step: int, losses: dict[str, float]) -> None:
            if step % 10 == 0 or step == total:
                text = " ".join(f"{k} {v:.4f}" for k, v in losses.items())
                bar.update(task, completed=step, losses=text)

        return fn(cb)


def _print_report(result) -> None:
    from rich.table import Table

    reg = result.task == "regression"
    fid = "fidelity (mse to original)" if reg else "fidelity (agreement)"
    for i, m in enumerate(result.metrics, 1):
        table = Table(
            title=f"user {i}: personalization {m['personalization']:.4f} "
            f"({'1 - mse/mse_base' if reg else 'accuracy'}, {m['samples']} validation samples)"
        )
        for col in ("keys", "n", "leakage mean [95% CI]", "leakage worst", fid + " mean", "worst"):
            table.add_column(col)
        for group in ("null", "random", "hamming1"):
            g = m[group]
            lk, fd = g["leakage"], g["fidelity"]
            table.add_row(
                group,
                str(lk["n"]),
                f"{lk['mean']:.4f} [{lk['ci95'][0]:.4f}, {lk['ci95'][1]:.4f}]",
                f"{lk['worst']:.4f}",
                f"{fd['mean']:.3g}",
                f"{fd['worst']:.3g}",
            )
        out.print(table)
    layers = ", ".join(f"{x['name']} ({x['features']})" for x in result.keyed_layers)
    out.print(f"wrote {result.out} (keyed layers: {layers})")
