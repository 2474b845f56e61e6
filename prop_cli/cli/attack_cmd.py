from __future__ import annotations

import sys
from pathlib import Path

import typer

from .common import err, fail, key_for_bundle, out, print_json


def attack(
    bundle: Path = typer.Argument(..., help="Bundle directory written by prop personalize."),
    data: Path = typer.Option(
        ..., "--data", help="The audited user's data .npz (x, y); x alone without a key."
    ),
    key_file: list[Path] = typer.Option(
        None, "--key-file", help="The audited user's key; repeat for other users' keys (cross-user)."
    ),
    passphrase: bool = typer.Option(
        False, "--passphrase", help="The audited user's key from their passphrase (key files: other users)."
    ),
    hamming: str = typer.Option(
        None, "--hamming", help="Hamming distances to probe: 1..8, 1,2,4 or 3 (default 1..8 with a key)."
    ),
    per_distance: int = typer.Option(256, "--per-distance", help="Keys per distance (all if fewer exist)."),
    random_keys: int = typer.Option(4096, "--random", help="Uniform random keys to probe."),
    search: str = typer.Option(
        "relaxed,latent", "--search", help="White-box searches: relaxed,latent or none."
    ),
    restarts: int = typer.Option(8, "--restarts", help="Restarts of each search."),
    search_steps: int = typer.Option(200, "--search-steps", help="Adam steps of each search."),
    samples: int = typer.Option(256, "--samples", help="Samples of --data to audit on."),
    original: str = typer.Option(
        None, "--original", help="Original checkpoint as reference (default: the bundle without a key)."
    ),
    seed: int = typer.Option(0, "--seed", help="Seed for probe keys, samples and search restarts."),
    device: str = typer.Option("cpu", "--device", help="cpu, auto or cuda[:N]."),
    json_path: Path = typer.Option(
        None, "--json", help="Write the report (schema prop-audit/1); - = stdout."
    ),
    plot_path: Path = typer.Option(None, "--plot", help="Write a PNG of leakage/fidelity vs distance."),
    max_leak: float = typer.Option(
        None, "--max-leak", help="Exit 1 if any probe group's worst-key leakage exceeds this."
    ),
    record: bool = typer.Option(False, "--record", help="Store the audit summary in the bundle manifest."),
    force: bool = typer.Option(False, "--force", help="Replace existing --json / --plot files."),
) -> None:
    """Audit how much of the personalization leaks to anyone holding BUNDLE without the key."""
    from prop_cli import audit_report
    from prop_cli.attack import (
        AuditSettings,
        apply_max_leak,
        audit,
        load_original,
        parse_hamming,
        parse_search,
    )
    from prop_cli.bundle import check_output, load_bundle
    from prop_cli.data import load_npz
    from prop_cli.keys import read_key_file

    key_file = key_file or []
    settings = AuditSettings(
        hamming=parse_hamming(hamming) if hamming is not None else None,
        per_distance=per_distance,
        random=random_keys,
        search=parse_search(search),
        restarts=restarts,
        search_steps=search_steps,
        samples=samples,
        seed=seed,
    )
    if max_leak is not None and not key_file and not passphrase:
        fail("--max-leak needs the user's key and targets", "pass --key-file with --data holding x and y")
    for path, what in ((json_path, "--json file"), (plot_path, "--plot file")):
        if path is not None and str(path) != "-":
            check_output(path, force, what=what)
    b = load_bundle(bundle)
    keys = []
    if passphrase:
        keys.append(key_for_bundle(None, True, b.manifest))
    keys += [read_key_file(p, b.key_bits) for p in key_file]
    ds = load_npz(data, require_y=bool(keys))
    ref = load_original(b, original) if original else None
    report = _with_progress(lambda cb: audit(b, ds, keys, settings, original=ref, device=device, progress=cb))
    failing = apply_max_leak(report, max_leak) if max_leak is not None else []
    if json_path is not None and str(json_path) != "-":
        from prop_cli.bundle import dump_json

        json_path.write_text(dump_json(report))
        err.print(f"wrote {json_path}")
    if plot_path is not None:
        audit_report.plot(report, plot_path)
        err.print(f"wrote {plot_path}")
    if record:
        audit_report.record(bundle, report)
        err.print(f"recorded the audit summary in {bundle}/manifest.json")
    if json_path is not None and str(json_path) == "-":
        print_json(report)
    else:
        out.print(audit_report.table(report))
    if failing:
        name, worst = max(failing, key=lambda f: f[1])
        more = f" (and {len(failing) - 1} more groups)" if len(failing) > 1 else ""
        print(
            f"prop: leak check failed: worst-key leakage {worst:.4f} in '{name}'{more} "
            f"exceeds --max-leak {max_leak}",
            file=sys.stderr,
        )
        raise typer.Exit(1)


def _with_progress(fn):
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(
        TextColumn("{task.description:<12}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total}"),
        TimeElapsedColumn(),
        console=err,
        transient=True,
    ) as bar:
        tasks: dict[str, int] = {}

        def cb(stage: str, done: int, total: int) -> None:
            if stage not in tasks:
                tasks[stage] = bar.add_task(stage, total=total)
            bar.update(tasks[stage], completed=done)

        return fn(cb)
