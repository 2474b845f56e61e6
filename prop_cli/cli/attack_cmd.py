from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer

from prop_cli.config import AuditSettings, parse_hamming, parse_list
from prop_cli.constants import AUDIT_SCHEMA, DEFAULT_DEVICE, DEFAULT_THREADS, MAX_LEAK
from prop_cli.errors import plural

from .common import err, fail, out, output_path, print_json, read_passphrase, stage_progress, warn
from .options import (
    AllowUnenrolledKey,
    BundleArch,
    BundleArg,
    Device,
    Force,
    Threads,
    TrustRemoteCode,
    config_options,
    opt,
)

# The audit settings attack exposes as --flags: AuditSettings field -> help (--probes and --hamming
# take comma lists and are parsed below).
SETTINGS = {
    "per_distance": "Keys per Hamming distance (all of them if fewer exist).",
    "random": "Uniform random keys to probe.",
    "restarts": "Restarts of each search.",
    "search_steps": "Adam steps of each search.",
    "search_lr": "Adam learning rate of the searches.",
    "search_batch": "Samples per search step (0: all of them).",
    "fewshot_restarts": "Restarts of the few-shot code fit (T3) [default: 128; 16 for LeRobot policies].",
    "fewshot_steps": "Adam steps of the few-shot code fit (T3).",
    "samples": "Samples of --data to audit on.",
    "blackbox": "Random keys of the black-box scan [default: 1,000,000; 65,536 for LeRobot policies].",
    "blackbox_screen": "Samples each black-box key is screened on.",
    "blackbox_keep": "Black-box keys kept per criterion and re-scored.",
    "seed": "Seed for probe keys, samples and search restarts.",
    "min_passphrase_years": "With --passphrase: fail if guessing it takes fewer core-years than this.",
    "noise_seed": "Seed of a sampling policy's noise (LeRobot Diffusion): every key's chunks start from it.",
    "budget": "Wall seconds the probes may take; then they stop and the report says what was cut or not "
    "tried [default: none; 600 for LeRobot policies].",
}


Data = Annotated[Path, opt("--data", "The audited user's data (x, y); x alone without a key.")]
KeyFiles = Annotated[list[Path] | None, opt("--key-file", "The audited user's key; repeat for others' keys.")]
UserPassphrase = Annotated[bool, opt("--passphrase", "The audited user's key from a passphrase.")]
CommaList = str | None
Probes = Annotated[CommaList, opt("--probes", "Probes to run, comma-separated, or none (default: all).")]
Search = Annotated[CommaList, opt("--search", "Older form of --probes: key probes + these searches.")]
Hamming = Annotated[CommaList, opt("--hamming", "Hamming distances: 1..8, 1,2,4 or 3 (default 1..8).")]
Original = Annotated[str | None, opt("--original", "Original checkpoint: reference output, controls' model.")]
JsonReport = Annotated[Path | None, opt("--json", f"Write the report ({AUDIT_SCHEMA}); - = stdout.")]
Plot = Annotated[Path | None, opt("--plot", "Write a PNG of leakage/fidelity vs distance.")]
MaxLeak = Annotated[
    float | None, opt("--max-leak", "Exit 1 if a row leaks more than this beyond its control "
                                    f"(the docs use {MAX_LEAK:g}; personalize warns beyond it).")
]  # fmt: skip
Record = Annotated[bool, opt("--record", "Store the audit summary in the bundle manifest.")]


@config_options(AuditSettings, SETTINGS, into="settings")
def attack(
    bundle: BundleArg, data: Data, settings: AuditSettings,
    key_file: KeyFiles = None, passphrase: UserPassphrase = False,
    probes: Probes = None, search: Search = None, hamming: Hamming = None, original: Original = None,
    device: Device = DEFAULT_DEVICE, threads: Threads = DEFAULT_THREADS,
    json_path: JsonReport = None, plot_path: Plot = None, max_leak: MaxLeak = None, record: Record = False,
    force: Force = False, trust_remote_code: TrustRemoteCode = False, arch: BundleArch = None,
    allow_unenrolled_key: AllowUnenrolledKey = False,
) -> None:  # fmt: skip
    """Audit how much of the personalization leaks to anyone holding BUNDLE without the key."""
    from prop_cli.api import apply_max_leak, audit_bundle, record_audit
    from prop_cli.api import select_probes as select
    from prop_cli.files import (
        AUDIT_REPORT,
        PLOT,
        check_not_input,
        check_output,
        check_writable,
        dump_json,
        write_text,
    )
    from prop_cli.present import check_plot
    from prop_cli.present import decision as audit_decision
    from prop_cli.present import plot as plot_audit
    from prop_cli.present import table as audit_table

    key_file = key_file or []
    if probes is not None or search is not None:
        settings.probes = select(
            parse_list(probes, "--probes") if probes is not None else None,
            parse_list(search, "--search") if search is not None else None,
        )
    settings.hamming = parse_hamming(hamming) if hamming is not None else None
    if max_leak is not None and not key_file and not passphrase:
        fail("--max-leak needs the user's key and targets", "pass --key-file with --data holding x and y")
    if plot_path is not None:
        check_plot()  # before the probes: an extra missing is known now, not after minutes of work
    json_file = output_path(json_path)
    outputs = [(json_file, "--json file", "--json", AUDIT_REPORT), (plot_path, "--plot file", "--plot", PLOT)]

    def check_outputs() -> None:  # before the probes, and again before writing (they take minutes)
        for path, what, flag, kind in outputs:
            if path is not None:
                check_not_input(path, flag, [bundle, data, *key_file, original])
                check_output(path, force, what=what, flag=flag, kind=kind)
        if record and Path(bundle).is_dir():  # the manifest is rewritten in place
            check_writable(bundle, "bundle", "--record", as_folder=False)

    check_outputs()
    phrase = read_passphrase() if passphrase else None
    report = stage_progress(
        lambda cb: audit_bundle(
            bundle, data, settings, key_files=key_file, passphrase=phrase, original=original, device=device,
            progress=cb, threads=threads, trust_remote_code=trust_remote_code, arch=arch,
            allow_unenrolled_key=allow_unenrolled_key,
        )
    )  # fmt: skip
    for w in report["warnings"]:
        warn(w)
    failing = apply_max_leak(report, max_leak) if max_leak is not None else []
    check_outputs()
    if json_file is not None:
        write_text(json_file, dump_json(report), what="--json file", flag="--json")
        err.print(f"wrote {json_file}")
    if plot_path is not None:
        plot_audit(report, plot_path)
        err.print(f"wrote {plot_path}")
    if record:
        record_audit(bundle, report)
        err.print(f"recorded the audit summary in {bundle}/manifest.json")
    if json_path is not None and json_file is None:
        print_json(report)
    else:  # the decision first, then the failing rows by severity, then the full table
        for line in audit_decision(report):
            out.print(line, highlight=False, markup=False, soft_wrap=True)
        out.print(audit_table(report))
    row = report.get("passphrase")
    if row is not None and not row["passed"]:
        print(
            f"prop: passphrase check failed: {row['core_years']:.3g} core-years to guess it, below "
            f"{row['min_core_years']:g}",
            file=sys.stderr,
        )
        raise typer.Exit(1)
    if max_leak is not None and not failing and not report["max_leak"]["passed"]:
        print(f"prop: leak check not done at --max-leak {max_leak}: no probe ran; a larger --budget, or "
              "fewer --samples, runs them", file=sys.stderr)  # fmt: skip
        raise typer.Exit(1)
    if failing:
        more = f" (and {plural(len(failing) - 1, 'more row')})" if len(failing) > 1 else ""
        print(f"prop: leak check failed at --max-leak {max_leak}: {report['max_leak']['reason']}{more}",
              file=sys.stderr)  # fmt: skip
        raise typer.Exit(1)
