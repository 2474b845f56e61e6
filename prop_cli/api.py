"""The library's front door: one function per CLI command, usable from Python as well.

Data path (docs/design.md): checkpoint (``adapters``) -> keyed model (``core``) -> training (``train``)
-> bundle (``bundle``) -> audit (``attack``) | shipping (``deploy``). The CLI parses, calls one function
here and prints; the work is done in those packages.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

import prop_adapters as adapters
from prop_adapters import CheckpointOptions
from prop_adapters.hub import resolve_checkpoint
from prop_cli import constants as C
from prop_cli.attack import apply_max_leak, audit, target
from prop_cli.attack.probes import select as select_probes
from prop_cli.bundle import load_bundle, read_manifest
from prop_cli.bundle.manifest import bundle_version, next_version
from prop_cli.bundle.read import load_sealed, rebuild_original
from prop_cli.bundle.records import (
    check_new_key,
    record_to_remove,
    rewrite_records,
    with_records,
)
from prop_cli.bundle.write import common_fields
from prop_cli.config import AuditSettings, EvalSettings, ExportSettings, PersonalizeConfig
from prop_cli.core.key_files import (
    KeySource,
    generate_key_file,
    key_for_bundle,
    read_key_file,
    user_keys,
)
from prop_cli.core.keyed_model import key_codes
from prop_cli.core.layers import describe_layer, keyable_layers, select_layers
from prop_cli.core.passphrase import check_strength as check_passphrase
from prop_cli.core.passphrase import strength
from prop_cli.datasources import SOURCES, load_data
from prop_cli.deploy.publish import push_bundle  # `prop push`: bundle, ONNX export and model card to the hub
from prop_cli.errors import PropError
from prop_cli.files import (
    EXPORT,
    PEFT,
    bundle_lock,
    check_not_input,
    check_output,
    check_writable,
    no_links,
)
from prop_cli.run import KeyedPolicy, run_bundle
from prop_cli.run.file import run_file
from prop_cli.run.inputs import load_inputs
from prop_cli.run.policy import require_array_model, require_enrolled, seed_noise
from prop_cli.threads import check as check_threads
from prop_cli.threads import configure as configure_threads
from prop_cli.train import User, personalize, settled
from prop_cli.train.added_user import added_user_config, train_added_user
from prop_cli.train.distributed import ranks_from_env
from prop_cli.train.report import sweep_gate

__all__ = [
    "AuditSettings",
    "CheckpointOptions",
    "EvalSettings",
    "ExportSettings",
    "KeySource",
    "KeyedPolicy",
    "PersonalizeConfig",
    "add_user",
    "apply_max_leak",
    "audit",
    "audit_bundle",
    "check_passphrase",
    "enrol",
    "eval_bundle",
    "export_bundle",
    "formats",
    "generate_key_file",
    "inspect_checkpoint",
    "key_codes",
    "key_for_bundle",
    "load_bundle",
    "load_inputs",
    "personalize_checkpoint",
    "describe_bundle",
    "export_peft_adapter",
    "is_bundle",
    "push_bundle",
    "read_key_file",
    "read_manifest",
    "record_audit",
    "remove_user",
    "run_bundle",
    "run_file",
    "select_probes",
    "serve_bundle",
    "serve_ray",
    "user_keys",
    "verify_bundle",
]


# Showing a report is prop_cli.present's (the CLI imports it there); these names stay importable from here.
_PRESENTATION = {"audit_decision": "decision", "audit_table": "table", "check_plot": "check_plot",
                 "plot_audit": "plot"}  # fmt: skip


def __getattr__(name: str):
    if name in _PRESENTATION:
        from prop_cli import present

        return getattr(present, _PRESENTATION[name])
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


@dataclass
class PersonalizeResult:
    out: Path
    task: str
    keyed_layers: list[dict]
    metrics: list[dict]
    final_losses: dict[str, float]
    manifest: dict = field(repr=False, default_factory=dict)
    processes: int = 1  # processes that trained it together (`accelerate launch`)
    written: bool = True  # False on every process but the first, which writes the bundle


def formats() -> dict:
    """The checkpoint formats and data formats prop reads, from their registries (`prop formats`)."""
    return {
        "checkpoints": [{"name": a.name, "summary": a.summary} for a in adapters.ADAPTERS],
        "data": [{"name": s.name, "summary": s.summary} for s in SOURCES],
    }


def _load(path: str, opts: CheckpointOptions | None) -> adapters.LoadedModel:
    return adapters.load_checkpoint(resolve_checkpoint(path), opts or CheckpointOptions())


def _parameters(module) -> int:
    return sum(p.numel() for p in module.parameters())


def inspect_checkpoint(
    path: str,
    opts: CheckpointOptions | None = None,
    layers: list[str] | None = None,
    exclude: list[str] | None = None,
) -> dict:
    """The linear layers and convolutions of a checkpoint, which of them would be keyed, and what its
    adapter knows. ``keyed_parameters``: the weights and biases of the keyed layers, the parameters a key
    acts on (``keyed_share`` of all)."""
    loaded = _load(path, opts)
    default = loaded.policy.default_layers if loaded.policy is not None else None
    chosen = set(select_layers(loaded.module, layers or default, exclude))
    total = _parameters(loaded.module)
    rows = [
        {**describe_layer(n, m), "kind": type(m).__name__, "parameters": _parameters(m), "keyed": n in chosen}
        for n, m in keyable_layers(loaded.module)
    ]
    keyed = sum(r["parameters"] for r in rows if r["keyed"])
    return {
        "checkpoint": str(path),
        "adapter": loaded.spec["adapter"],
        "model": adapters.describe(loaded),
        "input_shape": list(loaded.input_shape) if loaded.input_shape else None,
        "parameters": total,
        "keyed_parameters": keyed,
        "keyed_share": keyed / total if total else 0.0,
        "layers": rows,
    }


def personalize_checkpoint(
    checkpoint: str,
    users: list[tuple[Path, KeySource]],
    out: Path,
    cfg: PersonalizeConfig,
    *,
    opts: CheckpointOptions | None = None,
    general: Path | None = None,
    salt: bytes | None = None,
    device: str = "cpu",
    force: bool = False,
    progress: Callable[[int, dict[str, float]], None] | None = None,
    threads: int | None = None,
    status: Callable[[str], None] | None = None,
) -> PersonalizeResult:
    """Load a checkpoint, fine-tune it with the PRoP objective for the users, and write a bundle.

    ``users`` pairs each user's data file with their key (``core.key_files.user_keys`` builds them from key
    files and passphrases; ``salt`` is the passphrase salt it returns). ``threads``: torch's threads (None:
    ``prop_cli.threads`` chooses from the model's size and the idle cores). ``status`` hears what the run
    is doing outside its steps (loading, set-up, reports, writing), one line each.
    """
    bits = {len(k.bits) for _, k in users}
    if len(bits) > 1:
        raise PropError("the users' keys have different sizes", "give every user a key of the same size")
    if bits:
        cfg.check_key_bits(min(bits))
    check_threads(threads)
    check_not_input(out, "--out", [checkpoint, *(p for p, _ in users), general])
    check_output(out, force)  # before hours of training, not after
    ranks = ranks_from_env(device)  # one process, or those `accelerate launch` started
    say = status if status is not None and ranks.is_main else (lambda _: None)
    # --precision bf16: each weight held as the checkpoint stores it from the load on (a bf16 checkpoint
    # never in fp32: prop_cli.train.frozen); fp32: the model in fp32, as every other command loads it.
    bf16 = cfg.train.precision == "bf16"
    loaded = _load(checkpoint, replace(opts or CheckpointOptions(), keep_dtypes=bf16))
    cfg = settled(loaded, cfg)  # a default by the model's kind (--delta-pull) as the manifest records it
    configure_threads(_parameters(loaded.module), threads)
    datasets = [load_data(p) for p, _ in users]
    general_ds = load_data(general, require_y=False, flag="--general-data") if general is not None else None
    # Said once the files have been read (a bad file is one error line, with nothing before it).
    say(f"loaded {checkpoint} ({_parameters(loaded.module) / 1e6:.3g} M parameters) and the data of "
        f"{len(users)} user{'s' if len(users) != 1 else ''}")
    trained = personalize(
        loaded, [User(d, k.bits) for d, (_, k) in zip(datasets, users)], cfg, general=general_ds,
        device=device, progress=progress if ranks.is_main else None, ranks=ranks, status=status,
    )  # fmt: skip
    try:
        if not ranks.is_main:  # the first process writes the bundle; the others trained the same model
            return PersonalizeResult(out, trained.task, [], [], {}, processes=ranks.world, written=False)
        common = common_fields(loaded, [k for _, k in users], salt, cfg.to_dict(), checkpoint)
        say(f"writing {out}")
        written = trained.write(out, common, force=force)
        m = written.manifest
        # Each user's report gated as the audit gates (report.sweep_gate): what the CLI warns of.
        metrics = [u | {"gate": sweep_gate(u)} for u in written.metrics]
        return PersonalizeResult(
            out, m[C.M_TASK], m[C.M_KEYED_LAYERS], metrics, written.final_losses, m,
            processes=ranks.world,
        )  # fmt: skip
    finally:
        ranks.finish()


def audit_bundle(
    bundle_path: Path,
    data_path: Path,
    settings: AuditSettings,
    *,
    key_files: list[Path] = (),
    passphrase: str | None = None,
    original: str | None = None,
    device: str = "cpu",
    progress: Callable[[str, int, int], None] | None = None,
    threads: int | None = None,
    trust_remote_code: bool = False,
    arch: str | None = None,
    allow_unenrolled_key: bool = False,
) -> dict:
    """`prop attack`: the audit report for a bundle (``attack.audit``) from files. The audited user's key
    is the passphrase's if given, else the first key file; further key files are other users'. The
    audited key must be enrolled in the bundle (``allow_unenrolled_key``: audit it anyway); the audit's
    key rows measure the method for any key, enrolled or not."""
    check_threads(threads)
    bundle = load_bundle(bundle_path, trust_remote_code=trust_remote_code, arch=arch)
    configure_threads(bundle.parameters, threads)
    seed_noise(bundle.loaded, settings.noise_seed)
    keys = [] if passphrase is None else [key_for_bundle(bundle.manifest, passphrase=passphrase)]
    keys += [read_key_file(p, bundle.key_bits) for p in key_files]
    if keys:
        require_enrolled(bundle, keys[0], allow_unenrolled_key)
    bundle, data, settings = target.as_array(bundle, load_data(data_path, require_y=bool(keys)), settings)
    ref = target.load_original(bundle, original, trust_remote_code, settings.noise_seed) if original else None
    report = audit(bundle, data, keys, settings, original=ref, device=device, progress=progress)
    if passphrase is not None:
        # What guessing the passphrase offline costs: any record, enrolment or encoder tests a guess.
        report["passphrase"] = strength(passphrase, min_core_years=settings.min_passphrase_years).to_dict()
    return report


def describe_bundle(bundle_path: Path) -> dict:
    """`prop inspect BUNDLE`: mode, users, keyed layers, the recorded audit (which probes ran, and whether
    its --max-leak decision is a pass: ``attack.report.recorded_coverage``), whether a signature is
    present (not verified: `prop verify`), from the manifest, checked; nothing is imported and no key
    is needed."""
    from prop_cli.attack.report import recorded_coverage
    from prop_cli.bundle.describe import describe_bundle as describe
    from prop_cli.run.onnx import describe_export

    info = describe(Path(bundle_path))
    if info["audit"] is not None:
        info["audit"].update(recorded_coverage(info["audit"]))
    info["onnx_export"] = describe_export(Path(bundle_path) / C.EXPORT_DIR, read_manifest(Path(bundle_path)))
    return info


def is_bundle(path: str) -> bool:
    """Whether ``path`` is a bundle folder (has a manifest) rather than a checkpoint."""
    return (Path(path) / C.MANIFEST).is_file()


def record_audit(bundle_path: Path, report: dict) -> dict:
    """Store the audit's summary in the bundle's manifest (``audit``); weights and hashes untouched. A
    sealed bundle's summary holds verdicts only: no figure of its user (``attack.report.summary``)."""
    from prop_cli.attack.report import record
    from prop_cli.run.onnx import follow

    with bundle_lock(Path(bundle_path)):  # one writer from the read to the export's update, by descriptor
        old = read_manifest(Path(bundle_path))
        summary = record(Path(bundle_path), report)
        follow(Path(bundle_path) / C.EXPORT_DIR, old, read_manifest(Path(bundle_path)))  # stays the bundle's
    return summary


def export_peft_adapter(
    bundle_path: Path,
    out: Path,
    *,
    key_file: Path | None = None,
    passphrase: str | None = None,
    force: bool = False,
    trust_remote_code: bool = False,
    arch: str | None = None,
    allow_rollback: bool = False,
):
    """`prop export --peft`: the payload a key opens in a sealed bundle, as a standard peft LoRA adapter
    folder (``deploy.peft``); never written inside the bundle."""
    from prop_cli.deploy.peft import export_peft

    check_not_input(Path(out), "--peft", [bundle_path, key_file])
    check_output(Path(out), force, what="adapter folder", flag="--peft", kind=PEFT)
    bundle = load_bundle(
        bundle_path, trust_remote_code=trust_remote_code, arch=arch, allow_rollback=allow_rollback
    )
    key = key_for_bundle(bundle.manifest, key_file, passphrase)
    if key is None:
        raise PropError("--peft exports the payload your key opens", "pass --key-file or --passphrase")
    return export_peft(bundle, key, Path(out))


def export_lerobot_folder(
    bundle_path: Path, out: Path, *, resize_images: bool = False, force: bool = False,
    trust_remote_code: bool = False, allow_rollback: bool = False,
) -> Path:  # fmt: skip
    """`prop export --lerobot`: a LeRobot policy folder naming the bundle, for ``--policy.path`` in
    LeRobot's tools through the plugin ``lerobot_policy_prop`` (``deploy.lerobot_folder``); it holds no
    weights and no key. The bundle is verified here, and again each time the folder runs."""
    from prop_cli.deploy.lerobot_folder import write_lerobot_folder
    from prop_cli.files import LEROBOT_FOLDER

    check_not_input(Path(out), "--lerobot", [bundle_path])
    check_output(Path(out), force, what="LeRobot policy folder", flag="--lerobot", kind=LEROBOT_FOLDER)
    bundle = load_bundle(bundle_path, trust_remote_code=trust_remote_code, allow_rollback=allow_rollback)
    return write_lerobot_folder(bundle, Path(out), resize_images=resize_images)


def export_bundle(
    bundle_path: Path,
    out: Path | None = None,
    settings: ExportSettings | None = None,
    *,
    input_path: Path | None = None,
    key_file: Path | None = None,
    passphrase: str | None = None,
    force: bool = False,
    threads: int | None = None,
    trust_remote_code: bool = False,
    arch: str | None = None,
    allow_unenrolled_key: bool = False,
    allow_rollback: bool = False,
):
    """`prop export --onnx`: the bundle's graphs, verified against torch (``run.onnx.export_onnx``).
    The key (if given) is verified and bound to the graphs: `prop run --onnx` with it runs only these.
    A key enrolled in nothing is refused (``allow_unenrolled_key``: verified with, bound to nothing)."""
    from prop_cli.run.onnx import export_onnx, require_onnx

    check_threads(threads)
    target_dir = Path(out) if out is not None else no_links(Path(bundle_path), C.EXPORT_DIR)
    check_not_input(target_dir, "--out", [bundle_path, input_path, key_file], inside_ok=[bundle_path])
    check_output(target_dir, force, what="export folder", kind=EXPORT)  # before the bundle is loaded
    inside = Path(bundle_path).resolve() in Path(target_dir).resolve().parents
    # Written into the bundle (its onnx/, by default): one writer at a time, as for its other writes.
    with bundle_lock(Path(bundle_path)) if inside else contextlib.nullcontext():
        bundle = load_bundle(
            bundle_path, trust_remote_code=trust_remote_code, arch=arch, allow_rollback=allow_rollback
        )
        bundle = require_array_model(bundle, "prop export")
        require_onnx()
        configure_threads(bundle.parameters, threads)
        key = key_for_bundle(bundle.manifest, key_file, passphrase)
        x = load_inputs(input_path, bundle) if input_path is not None else None
        return export_onnx(
            bundle, out, settings, key=key, inputs=x, force=force, allow_unenrolled=allow_unenrolled_key
        )


def eval_bundle(
    bundle_path: Path, env_id: str, settings: EvalSettings | None = None, *,
    key_file: Path | None = None, passphrase: str | None = None, obs_map: str | None = None,
    metric: str | None = None, original: str | None = None, progress: Callable[[str], None] | None = None,
    vecnormalize: Path | None = None, video: Path | None = None, trust_remote_code: bool = False,
    arch: str | None = None, allow_unenrolled_key: bool = False, allow_rollback: bool = False,
    key_bits: str | None = None, flip_bit: int | None = None,
) -> dict:  # fmt: skip
    """`prop eval`: closed-loop rollouts of a bundle per key condition (``run.rollout``);
    ``key_bits`` (a 0/1 string) or ``flip_bit`` (a bit of the user's key): one wrong key again, as
    ``--json`` names it; a key enrolled in nothing is refused (``allow_unenrolled_key``: its row,
    ``key_not_enrolled``, runs the base);
    ``vecnormalize``: an SB3 VecNormalize pickle, read inertly (``adapters.sb3.vecnormalize``);
    ``video``: a new folder for one mp4 per condition."""
    from prop_adapters.sb3.vecnormalize import read_vecnormalize
    from prop_cli.run.rollout import check_video, evaluate_bundle, load_metric, parse_obs_map, probe_key

    settings = settings or EvalSettings()
    check_video(video)
    if video is not None:
        check_not_input(video, "--video", [bundle_path, key_file, vecnormalize])
    bundle = load_bundle(
        bundle_path, trust_remote_code=trust_remote_code, arch=arch, allow_rollback=allow_rollback
    )
    key = key_for_bundle(bundle.manifest, key_file, passphrase)
    settings.validate(has_key=key is not None)
    probe = probe_key(key, bundle.key_bits, key_bits, flip_bit)
    fn, mapping = load_metric(metric), parse_obs_map(obs_map)
    # The original rebuilt as the bundle's base is (its recorded spec: --arch and the rest need no repeat).
    ref = rebuild_original(bundle, original, trust_remote_code) if original else None
    for loaded in (bundle.loaded, ref):
        if loaded is not None:
            seed_noise(loaded, settings.noise_seed)
            if loaded.policy is not None:
                loaded.policy.instruction = settings.instruction
    normalizer = read_vecnormalize(vecnormalize) if vecnormalize is not None else None
    return evaluate_bundle(
        bundle, env_id, key, settings, obs_map=mapping, metric=fn, original=ref, progress=progress,
        normalizer=normalizer, video=video, allow_unenrolled=allow_unenrolled_key, probe=probe,
    )  # fmt: skip


def serve_bundle(
    bundle_path: Path, *, host: str = C.SERVE_HOST, port: int = C.SERVE_PORT, tls_cert: Path | None = None,
    tls_key: Path | None = None, allow_unenrolled_key: bool = False,
    max_connections: int = C.SERVE_MAX_CONNECTIONS, trust_remote_code: bool = False, arch: str | None = None,
    allow_rollback: bool = False, ready: Callable[[str], None] | None = None,
    batch_window_ms: float = C.SERVE_BATCH_WINDOW_MS, max_batch: int = C.SERVE_MAX_BATCH,
    cache_mb: float = C.SERVE_CACHE_MB, batch_no_key: bool = False,
) -> int:  # fmt: skip
    """`prop serve`: the bundle as an openpi websocket policy server until SIGINT/SIGTERM
    (``prop_cli.serve``); ``ready(url)`` once it listens. Returns the connections it served. The address
    and TLS are checked before the bundle is loaded. ``batch_no_key``: no-key requests share forwards
    (within float rounding of the original; by default each runs alone, bit for bit)."""
    try:
        from prop_cli.serve import PolicyServer
        from prop_cli.serve import serve_bundle as run_server
    except ImportError as e:
        raise PropError(f"prop serve needs {e.name}, which is not installed",
                        "pip install 'prop-keys[serve]'") from None  # fmt: skip
    from prop_cli.serve.server import tls_context

    tls_context(host, tls_cert, tls_key)  # a refused address says so before the model loads
    bundle = load_bundle(bundle_path, trust_remote_code=trust_remote_code, arch=arch,
                         allow_rollback=allow_rollback)  # fmt: skip
    server = PolicyServer(bundle, host=host, port=port, tls_cert=tls_cert, tls_key=tls_key,
                          allow_unenrolled=allow_unenrolled_key, max_connections=max_connections,
                          batch_window_ms=batch_window_ms, max_batch=max_batch,
                          cache_mb=cache_mb, batch_no_key=batch_no_key)  # fmt: skip
    return run_server(server, ready)


@dataclass
class UserChange:
    bundle: Path
    record: str  # the record id added or removed
    users: int  # users in the bundle afterwards
    metrics: dict | None = None  # add-user: the new user's report (as personalize prints it)
    export: dict | None = None  # add-user: the state of the bundle's ONNX export (describe_export)


def add_user(
    bundle_path: Path,
    data_path: Path,
    key: KeySource,
    *,
    cfg: PersonalizeConfig | None = None,
    device: str = "cpu",
    progress: Callable[[int, dict[str, float]], None] | None = None,
    trust_remote_code: bool = False,
    arch: str | None = None,
) -> UserChange:
    """`prop add-user`: train one more user's payload on their data alone and seal it into the bundle.

    Needs no other user's data or key. ``cfg`` defaults to the settings the bundle was made with; its
    payload kind, rank and layers must stay the bundle's (every record is enrolled in them). The
    manifest is written once, with the new record (no figure of the user goes in the clear)."""
    with bundle_lock(Path(bundle_path)):  # one writer at a time, from the read to the write
        bundle = load_sealed(bundle_path, "add-user", trust_remote_code, arch)
        check_writable(Path(bundle_path), "bundle", "BUNDLE", as_folder=False)  # now, not after training
        bundle.check_key(key.bits, "the new user's key")
        cfg = added_user_config(bundle, cfg)
        check_new_key(bundle.records, key.bits)
        next_version(bundle.manifest, str(bundle_path))  # a version left to write: refused before training
        configure_threads(bundle.parameters, None)
        rec, new, report = train_added_user(bundle, load_data(data_path), key.bits, cfg, device, progress)
        new = rewrite_records(Path(bundle_path), bundle.manifest, new, [rec])
        folder, export = no_links(Path(bundle_path), C.EXPORT_DIR), None
        if folder.exists():  # after the bundle: the export never holds more than it
            from prop_cli.run.onnx import add_record, describe_export

            add_record(folder, Path(bundle_path), bundle.manifest, new, rec.id)
            export = describe_export(folder, new)
    return UserChange(Path(bundle_path), rec.id, len(new[C.M_RECORDS]), report, export)


@dataclass
class Enrolled:
    bundle: Path
    status: str  # "enrolled", "re-enrolled (...)" or "already enrolled"
    format_version: int


def enrol(bundle_path: Path, key: np.ndarray, *, trust_remote_code: bool = False) -> Enrolled:
    """`prop enrol`: enrol your key in an unsealed bundle as it is now. Your consent that its current
    behaviour is yours: for a format 1-3 bundle you trust (from before enrolment, whose keys run its
    base), or to accept a change. Reads the bundle as data: nothing it names is imported. A bundle whose
    files name code (model.arch, a folder's factory, LeRobot processor steps) is refused as run refuses
    it, unless ``trust_remote_code``: enrolling is consent to run what it runs. Sealed bundles enrol
    each user in their own record (prop add-user)."""
    from prop_cli.bundle import check_files, enrol_key

    with bundle_lock(Path(bundle_path)):  # one writer at a time, from the read to the write
        manifest = read_manifest(Path(bundle_path))
        check_files(Path(bundle_path), manifest)
        named = adapters.remote_code(manifest[C.M_MODEL], str(bundle_path))  # reads files; imports nothing
        adapters.require_trust(named, f"bundle {bundle_path}", trust_remote_code)
        new, status = enrol_key(Path(bundle_path), manifest, key)
        if new is not manifest:
            from prop_cli.run.onnx import follow

            follow(Path(bundle_path) / C.EXPORT_DIR, manifest, new)  # the export stays the bundle's
    return Enrolled(Path(bundle_path), status, new[C.M_FORMAT])


def verify_bundle(
    folder: Path, *, public_key: Path | None = None, chain: list[Path] | tuple = (),
    allow_rollback: bool = False,
) -> dict:  # fmt: skip
    """`prop verify`: the publisher's signature over every file of a downloaded bundle (``deploy.sign``),
    then the bundle's own checks, as data (nothing it names is imported), then its version against the
    newest verified here from the same publisher (an older revision is refused unless
    ``allow_rollback``)."""
    from prop_cli.deploy.publish import verified_files
    from prop_cli.deploy.sign import check_revision, verify_folder

    result = verify_folder(Path(folder), public_key, chain)
    manifest, mode = verified_files(Path(folder))
    checked = check_revision(Path(folder), manifest, result.pop("signer_id"), allow_rollback)
    return {**result, "mode": mode.name, "users": mode.users(manifest), "format": manifest[C.M_FORMAT],
            "bundle_version": bundle_version(manifest), "rollback_checked": checked}  # fmt: skip


def remove_user(
    bundle_path: Path, *, key: np.ndarray | None = None, record: str | None = None,
    trust_remote_code: bool = False, arch: str | None = None,
) -> UserChange:  # fmt: skip
    """`prop remove-user`: delete one user's record, from the bundle and from its ONNX export
    (``<bundle>/onnx``) if it has one. Ownership is proven by the key: it must open the record it
    removes; or ``record`` (an id from `prop inspect`), for a bundle's maintainer when a user lost
    theirs (the rules: ``bundle.records.record_to_remove``)."""
    with bundle_lock(Path(bundle_path)):  # one writer at a time, from the read to the write
        bundle = load_sealed(bundle_path, "remove-user", trust_remote_code, arch)
        check_writable(Path(bundle_path), "bundle", "BUNDLE", as_folder=False)
        bits = None if key is None else bundle.check_key(key)
        record = record_to_remove(bundle.manifest, bundle.records, bits, record, str(bundle_path))
        new = with_records(bundle.manifest, [], [record])
        version = bundle_version(next_version(bundle.manifest, str(bundle_path)))  # refused: nothing written
        export = no_links(Path(bundle_path), C.EXPORT_DIR)
        if (export / C.EXPORT_META).is_file():
            from prop_cli.run.onnx import drop_record

            # First: the export never holds more than the bundle; it takes the version the removal writes.
            drop_record(export, record, version or None)
        new = rewrite_records(Path(bundle_path), bundle.manifest, new, [])
    return UserChange(Path(bundle_path), record, len(new[C.M_RECORDS]))


def serve_ray(
    bundle_path: Path, *, replicas: int = 2, users_per_replica: int = 64, address: str | None = None,
    num_cpus: int | None = None, replica_cpus: float = 1.0, host: str = C.SERVE_HOST,
    port: int = C.SERVE_PORT, tls_cert: Path | None = None, tls_key: Path | None = None,
    allow_unenrolled_key: bool = False, batch_window_ms: float = C.SERVE_BATCH_WINDOW_MS,
    max_batch: int = C.SERVE_MAX_BATCH, trust_remote_code: bool = False, arch: str | None = None,
    allow_rollback: bool = False, ready: Callable[[str], None] | None = None,
) -> None:  # fmt: skip
    """`prop serve-ray`: `prop serve` as a Ray Serve application (``prop_cli.serve.ray_app``) on a local
    Ray instance, or on the cluster at ``address``, until SIGINT/SIGTERM; ``ready(url)`` once deployed.
    The bundle, the options, the address and TLS are checked before Ray starts."""
    try:
        from prop_cli.serve.server import tls_context
    except ImportError as e:
        raise PropError(f"prop serve-ray needs {e.name}, which is not installed",
                        "pip install 'prop-keys[ray]'") from None  # fmt: skip
    tls_context(host, tls_cert, tls_key)  # a refused address says so before Ray or the model load
    try:
        from prop_cli.serve import ray_app
    except ImportError as e:
        raise PropError(f"prop serve-ray needs Ray Serve ({e.name} is not installed)",
                        "pip install 'prop-keys[ray]'") from None  # fmt: skip
    if address is not None and num_cpus is not None:
        raise PropError("--num-cpus sizes a local Ray instance; a cluster (--address) has its own",
                        "drop --num-cpus, or --address")  # fmt: skip
    bundle = load_bundle(bundle_path, trust_remote_code=trust_remote_code, arch=arch,
                         allow_rollback=allow_rollback)  # fmt: skip
    app = ray_app.application(
        Path(bundle_path), replicas=replicas, users_per_replica=users_per_replica,
        allow_unenrolled=allow_unenrolled_key, batch_window_ms=batch_window_ms, max_batch=max_batch,
        replica_cpus=replica_cpus, trust_remote_code=trust_remote_code, arch=arch,
        allow_rollback=allow_rollback, bundle=bundle,
    )  # fmt: skip
    ray_app.run_app(app, address=address, host=host, port=port, tls_cert=tls_cert, tls_key=tls_key,
                    num_cpus=num_cpus, ready=ready)  # fmt: skip
