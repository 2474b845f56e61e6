from __future__ import annotations

from pathlib import Path
from typing import Annotated

from prop_cli.config import TASKS, PersonalizeConfig
from prop_cli.constants import (
    DEFAULT_BUNDLE,
    DEFAULT_DEVICE,
    DEFAULT_THREADS,
    KEY_BITS_DEFAULT,
    KEY_ENCODINGS,
)
from prop_cli.errors import plural

from .common import checkpoint_options, fail, out, print_json, read_passphrase, training_progress, warn
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
    config_options,
    opt,
)

# The training settings personalize exposes, as --flags: PersonalizeConfig field -> help.
SETTINGS = {
    "steps": "Training steps.",
    "lr": "Adam learning rate of the key encoder (cosine decay).",
    "lr_floor": "The cosine decay ends at lr times this (1: a constant learning rate).",
    "base_lr_scale": "The base weights learn at lr times this.",
    "hamming_radius": "Keys up to this many bits off fall back (at most the key size).",
    "user_rows": "Rows of the users' data per step.",
    "null_rows": "Fallback samples per step, each run with no key.",
    "samples_per_key": "Fallback samples each sampled key runs on.",
    "random_keys": "K2: random keys per step.",
    "neighbour_keys": "K1: Hamming neighbours per step (0 = none: leaky, for audits).",
    "null_weight": "Weight of the no-key fallback loss.",
    "key_weight": "Weight of the random and neighbour keys' fallback loss.",
    "delta_pull": "Weight pulling wrong keys' layer scales to the no-key model's (0 = off).",
    "far_codes": "Codes 40-56 of 128 bits from yours per step, trained to fall back (0 = none).",
    "hard_negatives": "Worst-scoring random keys kept to train on (half of K2 each step; 0 = off).",
    "hard_pool": "Fresh random keys scored for --hard-negatives at each rescoring.",
    "hard_every": "Steps between the rescorings of --hard-negatives.",
    "fallback_noise": "Share of fallback inputs perturbed with noise (0 = the data only).",
    "val_fraction": "Share of each user's data held out for the final report.",
    "key_encoding": f"{KEY_ENCODINGS[0]} or {KEY_ENCODINGS[1]} (the paper's).",
    "freeze_base": "Train the encoder only: the base weights stay the original's.",
    "layers": "Layers to key: exact name, dotted suffix, regex or all-linear; repeat.",
    "exclude": "Layers not to key (same forms); repeat.",
    "task": " or ".join(TASKS) + " (default: decided against the model).",
    "seed": "Seed: the same seed and inputs give byte-identical weights (not with --harden).",
    "harden": "Hardened unsealed mode: code-space negatives and an unrecorded encoder init "
    "(docs/hardening.md).",
    "encoder_init": "seed (follows --seed) or os (fresh randomness; default with --harden).",
    "code_negatives": "Code-space fallback codes per step near your code (64 with --harden, else 0).",
    "code_flip_max": "Code-space negatives: at most this many bits flipped.",
    "code_relax_min": "Code-space negatives: relaxed at least this far from your code, in (0, 1].",
    "antipode_codes": "Codes 72-88 of 128 bits from yours per step, trained to fall back (16 with "
    "--harden, else 0).",
    "seal": "Sealed bundle: base = the original, each user's payload encrypted under their key.",
    "payload": "With --seal: lora, delta, full or peft-lora (what is stored per user; peft-lora exports "
    "as a standard peft adapter: prop export --peft).",
    "payload_rank": "With --seal --payload lora or peft-lora: the update's rank.",
    "payload_lr": "With --seal: Adam learning rate of the payload (cosine decay).",
    "precision": "fp32, or bf16: mixed precision (bf16 autocast; weights and Adam stay fp32).",
    "report_budget": "Policies: the final report's (key, held-out frame) sampler runs (default: by the "
    "policy's size; 0 = every key on every frame).",
}


Data = Annotated[list[Path], opt("--data", "Your data (x, y); repeat per user (`prop formats`).")]
KeyFiles = Annotated[list[Path] | None, opt("--key-file", "A user's key file; repeat.")]
Passphrases = Annotated[
    int,  # a count: no "[default: 0]" in --help
    opt("--passphrase", "Derive a key from a passphrase; repeat per user.", count=True, show_default=False),
]
Out = Annotated[Path, opt("--out", "Bundle directory to write.")]
General = Annotated[Path | None, opt("--general-data", "Inputs (x) on which the original must be kept.")]
Bits = Annotated[int, opt("--bits", "Key size for --passphrase.")]


@config_options(PersonalizeConfig, SETTINGS)
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
    cfg = config
    cfg.layers, cfg.exclude = cfg.layers or None, cfg.exclude or None
    cfg.validate(key_bits=bits if not key_file else None)
    # Before the passphrases are asked for and stretched, and before any training (the API checks again).
    check_not_input(out_path, "--out", [checkpoint, *data, general, *key_file])
    check_output(out_path, force)
    phrases = [read_passphrase(f"Passphrase for user {len(key_file) + i + 1}") for i in range(passphrase)]
    keys, salt = user_keys(key_file, phrases, bits, allow_weak=weak_passphrase)
    opts = checkpoint_options(arch, arch_kwargs, activation, trust_remote_code)
    result = training_progress(
        lambda cb: personalize_checkpoint(
            checkpoint, list(zip(data, keys)), out_path, cfg, opts=opts, general=general, salt=salt,
            device=device, force=force, progress=cb, threads=threads,
        ),
        cfg.steps, "personalize",
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
    parts = [f"{ran[k]} of {of[k]} {w}" for k, w in (("frames", "held-out frames"), *GROUPS.items())]
    warn(f"user {user}'s report covers {', '.join(parts)} (--report-budget {coverage['budget']}; 0 runs "
         "every key on every frame); prop attack audits further")  # fmt: skip


def _warn_gate(user: int, gate: dict) -> None:
    """One stderr line when a user's own wrong-key sweep leaks beyond the audit's --max-leak default."""
    if gate["passed"]:
        return
    worst = ", ".join(f"{GROUPS[g]} worst {gate['worst'][g]:.3f}" for g in gate["failing"])
    warn(f"user {user}'s wrong keys leak beyond --max-leak {gate['max_leak']:g} ({worst}); personalize again "
         "with more --steps or --random-keys, or --seal; prop attack audits it")  # fmt: skip
