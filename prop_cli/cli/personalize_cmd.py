from __future__ import annotations

from pathlib import Path
from typing import Annotated

from prop_cli.config import PersonalizeConfig, cli_settings
from prop_cli.constants import (
    DEFAULT_BUNDLE,
    DEFAULT_DEVICE,
    DEFAULT_THREADS,
    KEY_BITS_DEFAULT,
)
from prop_cli.errors import plural

from .common import (
    DRIFT_FIX,
    StatusLines,
    checkpoint_options,
    fail,
    out,
    print_json,
    read_passphrase,
    training_progress,
    warn,
)
from .options import (
    Activation,
    Arch,
    ArchKwargs,
    Checkpoint,
    Device,
    Force,
    Json,
    Threads,
    TrustRemoteCode,
    WeakPassphrase,
    opt,
    settings_options,
)

Data = Annotated[list[Path], opt("--data", "Your data (x, y); repeat per user (`prop formats`).")]
KeyFiles = Annotated[list[Path] | None, opt("--key-file", "A user's key file; repeat.")]
Passphrases = Annotated[
    int,  # a count: no "[default: 0]" in --help
    opt("--passphrase", "Derive a key from a passphrase; repeat per user.", count=True, show_default=False),
]
Out = Annotated[Path, opt("--out", "Bundle directory to write.")]
General = Annotated[Path | None, opt("--general-data", "Inputs (x) on which the original must be kept.")]
Bits = Annotated[int, opt("--bits", "Key size for --passphrase.")]


# Every training setting, its flag, default and help read from its field (prop_cli.config).
@settings_options(cli_settings(), PersonalizeConfig.of)
def personalize(
    checkpoint: Checkpoint,
    data: Data,
    config: PersonalizeConfig,
    key_file: KeyFiles = None,
    passphrase: Passphrases = 0,
    out_path: Out = Path(DEFAULT_BUNDLE),
    general: General = None,
    arch: Arch = None,
    arch_kwargs: ArchKwargs = None,
    activation: Activation = None,
    bits: Bits = KEY_BITS_DEFAULT,
    device: Device = DEFAULT_DEVICE,
    threads: Threads = DEFAULT_THREADS,
    force: Force = False,
    as_json: Json = False,
    trust_remote_code: TrustRemoteCode = False,
    weak_passphrase: WeakPassphrase = False,
) -> None:
    """Fine-tune CHECKPOINT so it behaves the users' way with their key, and like the original without.

    To export your behaviour later as a peft LoRA adapter (prop export --peft), personalize with --seal
    --payload peft-lora: no other bundle exports one."""
    from prop_cli.api import personalize_checkpoint, user_keys
    from prop_cli.files import check_not_input, check_output

    key_file = key_file or []
    if not key_file and not passphrase:
        fail("no key given", "pass --key-file (make one with prop keygen) or --passphrase")
    if len(key_file) + passphrase != len(data):
        fail(
            f"{len(data)} --data but {plural(len(key_file) + passphrase, 'key')}",
            "give one key per --data: key files first, then passphrases, in the same order",
        )
    cfg = config  # checked as it was built (PersonalizeConfig.of); the key size with passphrase keys
    if not key_file:
        cfg.check_key_bits(bits)
    # Before the passphrases are asked for and stretched, and before any training (the API checks again).
    check_not_input(out_path, "--out", [checkpoint, *data, general, *key_file])
    check_output(out_path, force)
    phrases = [read_passphrase(f"Passphrase for user {len(key_file) + i + 1}") for i in range(passphrase)]
    keys, salt = user_keys(key_file, phrases, bits, allow_weak=weak_passphrase)
    opts = checkpoint_options(arch, arch_kwargs, activation, trust_remote_code)
    with StatusLines("personalize") as status:
        result = training_progress(
            lambda cb: personalize_checkpoint(
                checkpoint, list(zip(data, keys)), out_path, cfg, opts=opts, general=general, salt=salt,
                device=device, force=force, progress=cb, threads=threads, status=status,
            ),
            cfg.train.steps, "personalize",
        )  # fmt: skip
    if not result.written:  # another process of `accelerate launch` writes and reports
        return
    if as_json:
        print_json({"bundle": str(result.out), "task": result.task, "keyed_layers": result.keyed_layers,
                    "metrics": result.metrics, "final_losses": result.final_losses,
                    "processes": result.processes})  # fmt: skip
    else:
        _print_report(result)
    for i, m in enumerate(result.metrics, 1):  # after the report, as the audit's decision
        _warn_coverage(i, m.get("coverage"))
        _warn_gate(i, m["gate"])
        _warn_lean(i, m)


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
            lk, fd = m[group]["leakage"], m[group]["fidelity"]
            table.add_row(
                group, str(lk["n"]), f"{lk['mean']:.4f} [{lk['ci95'][0]:.4f}, {lk['ci95'][1]:.4f}]",
                f"{lk['worst']:.4f}", f"{fd['mean']:.3g}", f"{fd['worst']:.3g}",
            )  # fmt: skip
        out.print(table)
    layers = ", ".join(f"{x['name']} ({x['features']})" for x in result.keyed_layers)
    records = [r["id"] for r in result.manifest.get("records", [])]
    sealed = f"; sealed, user records {', '.join(records)}" if records else ""
    together = f"; trained on {result.processes} processes" if result.processes > 1 else ""
    out.print(f"wrote {result.out} (keyed layers: {layers}{sealed}{together})")


GROUPS = {"random": "random keys", "hamming1": "one-bit neighbours"}


def _warn_coverage(user: int, coverage: dict | None) -> None:
    """One stderr line when a policy's report ran within its budget (--report-budget), not every key on
    every held-out frame: what it covered, of what."""
    if not coverage:
        return
    ran, of = coverage["ran"], coverage["of"]
    # A sealed policy's report cuts frames only (its wrong keys open nothing and cost no sampler run).
    groups = (("frames", "held-out frames"), *GROUPS.items())
    parts = [f"{ran[k]} of {of[k]} {w}" for k, w in groups if k in ran]
    warn(f"user {user}'s report covers {', '.join(parts)} (--report-budget {coverage['budget']}; 0 runs "
         "every key on every frame); prop attack audits further")  # fmt: skip


def _warn_gate(user: int, gate: dict) -> None:
    """One stderr line when a user's own wrong-key sweep leaks beyond the audit's --max-leak default."""
    if gate["passed"]:
        return
    worst = ", ".join(f"{GROUPS[g]} worst {gate['worst'][g]:.3f}" for g in gate["failing"])
    warn(f"user {user}'s wrong keys leak beyond --max-leak {gate['max_leak']:g} ({worst}); personalize again "
         "with more --steps or --random-keys, or --seal; prop attack audits it")  # fmt: skip


def _warn_lean(user: int, m: dict) -> None:
    """One stderr line when a group's wrong keys move systematically towards the user's change (a sign
    test over the keys, p < 0.05), however small each move: the user's behaviour carried to every wrong
    key, which per-key leakage (clipped at 0) cannot show and a closed loop's success threshold can turn
    into lost episodes (docs/metrics.md, "Systematic drift"). A lean away is in --json only."""
    for group, words in GROUPS.items():
        lean = m.get(group, {}).get("lean")
        if not lean or not lean["systematic"] or lean["above"] <= lean["below"]:
            continue
        warn(f"user {user}'s {words} drift systematically towards your change ({lean['above']} of "
             f"{lean['keys']} keys, sign test p = {lean['p']:.2g}, mean lean {lean['mean']:+.3g}); "
             f"check them in closed loop with prop eval --original; {DRIFT_FIX}")  # fmt: skip
