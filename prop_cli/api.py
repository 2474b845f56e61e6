"""The library's front door: one function per CLI command, usable from Python as well.

Data path (docs/design.md): checkpoint -> adapter -> keyed model -> trainer -> bundle -> attack | export.
The CLI parses, calls one function here and prints; everything else lives in the modules named below.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

import prop_adapters
from prop_adapters import CheckpointOptions

from . import constants as C
from .audit import apply_max_leak, audit, load_original
from .bundle import Bundle, describe_layers, load_bundle, read_manifest, write_bundle, write_sealed_bundle
from .config import BLACKBOX_KEYS_POLICY, AuditSettings, EvalSettings, ExportSettings, PersonalizeConfig
from .datasources import SOURCES, load_data
from .datasources.npz import read_npy
from .errors import PropError
from .files import check_output, write_file
from .hub import resolve_checkpoint
from .keyed import key_codes
from .keys import KeySource, generate_key_file, kdf_record, key_for_bundle, new_salt, read_key_file
from .layers import linear_layers, select_layers
from .policy import KeyedPolicy
from .publish import push_bundle  # `prop push`: bundle, ONNX export and model card to the hub
from .threads import check as check_threads
from .threads import configure as configure_threads
from .trainer import User, personalize

__all__ = [
    "AuditSettings",
    "CheckpointOptions",
    "ExportSettings",
    "KeySource",
    "KeyedPolicy",
    "PersonalizeConfig",
    "apply_max_leak",
    "audit",
    "EvalSettings",
    "audit_bundle",
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
    "push_bundle",
    "read_key_file",
    "record_audit",
    "add_user",
    "remove_user",
    "run_bundle",
    "run_file",
]


@dataclass
class PersonalizeResult:
    out: Path
    task: str
    keyed_layers: list[dict]
    metrics: list[dict]
    final_losses: dict[str, float]
    manifest: dict = field(repr=False, default_factory=dict)


def formats() -> dict:
    """The checkpoint formats and data formats prop reads, from their registries (`prop formats`)."""
    return {
        "checkpoints": [{"name": a.name, "summary": a.summary} for a in prop_adapters.ADAPTERS],
        "data": [{"name": s.name, "summary": s.summary} for s in SOURCES],
    }


def _load(path: str, opts: CheckpointOptions | None) -> prop_adapters.LoadedModel:
    return prop_adapters.load_checkpoint(resolve_checkpoint(path), opts or CheckpointOptions())


def inspect_checkpoint(
    path: str,
    opts: CheckpointOptions | None = None,
    layers: list[str] | None = None,
    exclude: list[str] | None = None,
) -> dict:
    """The linear layers of a checkpoint, which of them would be keyed, and what its adapter knows."""
    loaded = _load(path, opts)
    default = loaded.policy.default_layers if loaded.policy is not None else None
    chosen = set(select_layers(loaded.module, layers or default, exclude))
    return {
        "checkpoint": str(path),
        "adapter": loaded.spec["adapter"],
        "model": prop_adapters.describe(loaded),
        "input_shape": list(loaded.input_shape) if loaded.input_shape else None,
        "parameters": _parameters(loaded.module),
        "layers": [
            {"name": n, "in_features": m.in_features, "out_features": m.out_features, "keyed": n in chosen}
            for n, m in linear_layers(loaded.module)
        ],
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
) -> PersonalizeResult:
    """Load a checkpoint, fine-tune it with the PRoP objective for the users, and write a bundle.

    ``users`` pairs each user's data file with their key (``keys.user_keys`` builds them from key files
    and passphrases; ``salt`` is the passphrase salt it returns). ``threads``: torch's threads (None:
    ``prop_cli.threads`` chooses from the model's size and the idle cores).
    """
    bits = {len(k.bits) for _, k in users}
    if len(bits) > 1:
        raise PropError("the users' keys have different sizes", "give every user a key of the same size")
    cfg.validate(key_bits=min(bits) if bits else None)
    check_threads(threads)
    check_output(out, force)  # before hours of training, not after
    loaded = _load(checkpoint, opts)
    configure_threads(_parameters(loaded.module), threads)
    datasets = [load_data(p) for p, _ in users]
    if cfg.seal:
        if general is not None:
            raise PropError(
                "--general-data does nothing with --seal (the base stays the original)", "drop --general-data"
            )
        return _personalize_sealed(
            checkpoint, loaded, datasets, users, out, cfg, salt, device, force, progress
        )
    general_ds = load_data(general, require_y=False, flag="--general-data") if general is not None else None
    result = personalize(
        loaded,
        [User(d, k.bits) for d, (_, k) in zip(datasets, users)],
        cfg,
        general=general_ds,
        device=device,
        progress=progress,
    )
    kinds = sorted({k.kind for _, k in users})
    keyed = result.keyed
    manifest = {
        C.M_MODEL: loaded.spec,
        C.M_KEYED_LAYERS: describe_layers(keyed),
        C.M_KEY: {
            "bits": bits.pop(),
            "encoding": cfg.key_encoding,
            "users": len(users),
            "source": kinds[0] if len(kinds) == 1 else "mixed",
            "kdf": kdf_record(salt),
        },
        C.M_ENCODER: {
            "hidden": list(cfg.encoder_hidden),
            "scale": cfg.delta_scale,
            "activation": "tanh",
            "output": "1 + scale * tanh",
        },
        C.M_CONFIG: cfg.to_dict(),
        C.M_TASK: result.task,
        C.M_IO: {"input_shape": _input_shape(loaded, datasets[0]), "checkpoint": str(checkpoint)},
        C.M_METRICS: {"users": result.metrics, "final_losses": result.final_losses},
    }
    copy_base = cfg.freeze_base and str(loaded.source).endswith(".safetensors")
    keyed.to("cpu")
    write_bundle(out, loaded=loaded, keyed=keyed, manifest=manifest, force=force, copy_base=copy_base)
    return PersonalizeResult(
        out, result.task, manifest[C.M_KEYED_LAYERS], result.metrics, result.final_losses, manifest
    )


def _input_shape(loaded: prop_adapters.LoadedModel, data) -> list[int] | dict[str, list[int]]:
    """Per-sample input shape; per feature name for policies with several inputs."""
    if loaded.policy is not None:
        return {k: list(v) for k, v in loaded.policy.input_features.items()}
    return list(data.x.shape[1:])


def _array_model(bundle: Bundle, command: str) -> Bundle:
    """Refuse, in one line, bundles of policies with named observation features where a command
    has no policy path yet (export)."""
    if bundle.loaded.policy is not None:
        raise PropError(
            f"{command} takes array models; {bundle.path} is a {bundle.loaded.spec['adapter']} policy "
            "with named observation features",
            "run it with prop run or prop eval (ONNX export of such policies is not there yet)",
        )
    return bundle


def _personalize_sealed(checkpoint, loaded, datasets, users, out, cfg, salt, device, force, progress):
    from .bundle import update_manifest
    from .sealed import check_distinct, public_metrics, train_users, user_report

    keys = [k.bits for _, k in users]
    check_distinct(keys)
    trained, task, axes = train_users(loaded, datasets, keys, cfg.task, cfg, device, progress)
    kinds = sorted({k.kind for _, k in users})
    layers = trained[0].payload.spec.layers
    manifest = {
        C.M_MODEL: loaded.spec,
        C.M_KEYED_LAYERS: [
            {
                "name": x["name"],
                "features": x["in_features"],
                **({C.M_BATCH_AXIS: axes[x["name"]]} if axes.get(x["name"]) else {}),
            }
            for x in layers
        ],  # fmt: skip
        C.M_PAYLOAD: trained[0].payload.spec.to_dict(),
        # A sealed bundle always has a passphrase salt, so passphrase users can be added later.
        # No user count: the records list is the count, and add-user / remove-user keep it true.
        C.M_KEY: {
            "bits": len(keys[0]),
            "source": kinds[0] if len(kinds) == 1 else "mixed",
            "kdf": kdf_record(salt or new_salt()),
        },
        C.M_CONFIG: cfg.to_dict(),
        C.M_TASK: task,
        C.M_IO: {"input_shape": _input_shape(loaded, trained[0].val), "checkpoint": str(checkpoint)},
    }
    written = write_sealed_bundle(
        out, loaded=loaded, manifest=manifest, users=[(u.payload, u.private, u.bits) for u in trained],
        force=force,
    )  # fmt: skip
    bundle = _report_view(out)
    reports = [user_report(bundle, u, cfg, i) for i, u in enumerate(trained)]
    records = written[C.M_RECORDS]
    update_manifest(
        out, C.M_METRICS, {"users": [public_metrics(r, e["id"]) for r, e in zip(reports, records)]}
    )
    final = reports[0].pop("final_losses", {})
    for r in reports[1:]:
        r.pop("final_losses", None)
    return PersonalizeResult(out, task, written[C.M_KEYED_LAYERS], reports, final, read_manifest(out))


def _report_view(path: Path) -> Bundle:
    """A written bundle as the per-user report runs it: policies through their array view."""
    bundle = load_bundle(path)
    if bundle.loaded.policy is None:
        return bundle
    from .policy_view import array_bundle

    return array_bundle(bundle)


def _parameters(module) -> int:
    return sum(p.numel() for p in module.parameters())


def load_inputs(path: Path, bundle: Bundle, flag: str = "--input") -> np.ndarray:
    """Inputs for `prop run`: a .npy array, or the ``x`` of a data file; checked against the bundle."""
    path = Path(path)
    if path.suffix == ".npy":
        if not path.is_file():
            raise PropError(f"{flag} {path} does not exist", "give a .npy or .npz file")
        fix = "save inputs with numpy.save"
        x = read_npy(lambda: np.load(path, allow_pickle=False), f"{flag} {path}", fix)
        if not isinstance(x, np.ndarray) or x.ndim == 0:
            raise PropError(f"{flag} {path} holds no array of samples", fix)
        if x.dtype.kind not in "fiu" or not np.isfinite(x).all():
            raise PropError(f"{flag} {path} must hold finite numbers", "check the array")
        x = x.astype(np.float32)
    else:
        x = load_data(path, require_y=False, min_samples=1, flag=flag).x
    want = tuple(bundle.manifest[C.M_IO]["input_shape"])
    if x.shape[1:] != want:
        if x.shape == want:
            x = x[None]  # a single sample
        else:
            raise PropError(
                f"{flag} {path}: samples have shape {x.shape[1:]}, the bundle expects {want}",
                "give an array of shape (N, " + ", ".join(map(str, want)) + ")",
            )
    return x


def run_bundle(bundle: Bundle, x: np.ndarray, key: np.ndarray | None) -> np.ndarray:
    """The bundle's raw outputs on ``x``: with a key, that key's behaviour; without, the base's.

    One call folds the key once; in a control loop keep a ``KeyedPolicy(bundle, key)`` instead.
    """
    return KeyedPolicy(bundle, key)(x)


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
) -> RunResult:
    """`prop run`: outputs for the inputs in a file, written to ``output`` (.npy), with or without a key."""
    check_threads(threads)
    check_output(output, force, what="output", flag="--output")
    bundle = load_bundle(bundle_path)
    n_threads = configure_threads(_parameters(bundle.keyed or bundle.loaded.module), threads)
    key = key_for_bundle(bundle.manifest, key_file, passphrase)
    if bundle.loaded.policy is not None:
        if onnx or onnx_dir is not None:
            raise PropError(f"--onnx: {bundle.path} is a policy, which has no ONNX export yet", "drop --onnx")
        from .policy_view import run_policy

        data = load_data(input_path, require_y=False, min_samples=1, flag="--input")
        y = run_policy(bundle, data, key)
    elif onnx or onnx_dir is not None:
        x = load_inputs(input_path, bundle)
        from .onnx_runtime import run_onnx

        y = run_onnx(bundle, x, key, onnx_dir, threads=n_threads)
    else:
        y = run_bundle(bundle, load_inputs(input_path, bundle), key)

    def save(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            np.save(f, y)

    write_file(output, save, what="output", flag="--output")
    # A key that opens no record of a sealed bundle ran the base: report it as such, not as keyed.
    keyed = key is not None and (not bundle.is_sealed or bundle.sealed.open(key) is not None)
    return RunResult(Path(output), tuple(y.shape), keyed, onnx or onnx_dir is not None)


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
) -> dict:
    """`prop attack`: the audit report for a bundle (``audit.audit``) from files. The audited user's key
    is the passphrase's if given, else the first key file; further key files are other users'."""
    check_threads(threads)
    bundle = load_bundle(bundle_path)
    configure_threads(_parameters(bundle.keyed or bundle.loaded.module), threads)
    keys = [] if passphrase is None else [key_for_bundle(bundle.manifest, passphrase=passphrase)]
    keys += [read_key_file(p, bundle.key_bits) for p in key_files]
    data = load_data(data_path, require_y=bool(keys))
    if bundle.loaded.policy is not None:  # named features and action chunks, flattened (policy_view)
        from .policy_view import array_bundle, flat_dataset

        data = flat_dataset(bundle.loaded.policy, data, "--data")
        bundle = array_bundle(bundle)
        if settings.blackbox is None:
            settings = replace(settings, blackbox=BLACKBOX_KEYS_POLICY)
    ref = load_original(bundle, original) if original else None
    return audit(bundle, data, keys, settings, original=ref, device=device, progress=progress)


def record_audit(bundle_path: Path, report: dict) -> dict:
    """Store the audit's summary in the bundle's manifest (``audit``); weights and hashes untouched."""
    from .audit_report import record

    return record(Path(bundle_path), report)


def export_bundle(
    bundle_path: Path,
    out: Path | None = None,
    settings: ExportSettings | None = None,
    *,
    key_file: Path | None = None,
    passphrase: str | None = None,
    input_path: Path | None = None,
    force: bool = False,
    threads: int | None = None,
):
    """`prop export --onnx`: the four graphs, verified against torch (``export.export_onnx``)."""
    from .export import export_onnx
    from .onnx_runtime import require_onnx

    check_threads(threads)
    bundle = _array_model(load_bundle(bundle_path), "prop export")
    require_onnx()
    configure_threads(_parameters(bundle.keyed or bundle.loaded.module), threads)
    key = key_for_bundle(bundle.manifest, key_file, passphrase)
    x = load_inputs(input_path, bundle) if input_path is not None else None
    return export_onnx(bundle, out, settings, key=key, inputs=x, force=force)


def eval_bundle(
    bundle_path: Path,
    env_id: str,
    settings: EvalSettings | None = None,
    *,
    key_file: Path | None = None,
    passphrase: str | None = None,
    obs_map: str | None = None,
    metric: str | None = None,
    original: str | None = None,
    progress: Callable[[str], None] | None = None,
    vecnormalize: Path | None = None,
    video: Path | None = None,
) -> dict:
    """`prop eval`: closed-loop rollouts of a bundle per key condition (``rollout.evaluate_bundle``);
    ``vecnormalize``: an SB3 VecNormalize pickle, read inertly (``prop_cli.vecnormalize``); ``video``:
    a new folder for one mp4 per condition."""
    from .rollout import check_video, evaluate_bundle, load_metric, parse_obs_map
    from .vecnormalize import read_vecnormalize

    settings = settings or EvalSettings()
    check_video(video)
    bundle = load_bundle(bundle_path)
    key = key_for_bundle(bundle.manifest, key_file, passphrase)
    settings.validate(has_key=key is not None)
    fn, mapping = load_metric(metric), parse_obs_map(obs_map)
    ref = _load(original, None) if original else None
    normalizer = read_vecnormalize(vecnormalize) if vecnormalize is not None else None
    return evaluate_bundle(
        bundle, env_id, key, settings, obs_map=mapping, metric=fn, original=ref, progress=progress,
        normalizer=normalizer, video=video,
    )  # fmt: skip


def _sealed_bundle(bundle_path: Path, command: str) -> Bundle:
    bundle = load_bundle(bundle_path)
    if not bundle.is_sealed:
        raise PropError(
            f"{command} works on sealed bundles; {bundle_path} is unsealed (its users share one encoder and "
            "base, trained together)",
            "personalize again with every user's data, or with --seal to make users independent",
        )
    return bundle


@dataclass
class UserChange:
    bundle: Path
    record: str  # the record id added or removed
    users: int  # users in the bundle afterwards
    metrics: dict | None = None  # add-user: the new user's report (as personalize prints it)


def add_user(
    bundle_path: Path,
    data_path: Path,
    key: KeySource,
    *,
    cfg: PersonalizeConfig | None = None,
    device: str = "cpu",
    progress: Callable[[int, dict[str, float]], None] | None = None,
) -> UserChange:
    """`prop add-user`: train one more user's payload on their data alone and seal it into the bundle.

    Needs no other user's data or key. ``cfg`` defaults to the settings the bundle was made with; its
    payload kind, rank and layers must stay the bundle's (they are bound into every record)."""
    from .bundle import update_manifest
    from .config import PersonalizeConfig as Cfg
    from .sealed import (
        check_new_key,
        public_metrics,
        rewrite_records,
        seal_payload,
        train_users,
        user_report,
    )

    bundle = _sealed_bundle(bundle_path, "add-user")
    m = bundle.manifest
    bundle.check_key(key.bits, "the new user's key")
    base_cfg = Cfg.from_dict(m[C.M_CONFIG])
    cfg = cfg or base_cfg
    spec = m[C.M_PAYLOAD]
    if (cfg.payload, cfg.payload_rank if cfg.payload == "lora" else 0) != (spec["kind"], spec["rank"]):
        raise PropError(
            f"--payload {cfg.payload} (rank {cfg.payload_rank}) differs from the bundle's {spec['kind']} "
            f"(rank {spec['rank']})",
            "drop --payload/--payload-rank: every user of a bundle has the same payload layout",
        )
    cfg.layers = [x["name"] for x in spec["layers"]]
    cfg.exclude = None
    cfg.seal = True
    cfg.validate(key_bits=bundle.key_bits)
    check_new_key(bundle.sealed, key.bits)
    configure_threads(_parameters(bundle.loaded.module), None)
    index = len(m[C.M_RECORDS])
    [user], _, _ = train_users(
        bundle.loaded, [load_data(data_path)], [key.bits], cfg.task or bundle.task, cfg, device, progress,
        first_index=index,
    )  # fmt: skip
    rec = seal_payload(m, user.private, user.payload, key.bits)
    new = rewrite_records(Path(bundle_path), m, [rec], [])
    report = user_report(_report_view(Path(bundle_path)), user, cfg, index)
    users = list((new.get(C.M_METRICS) or {}).get("users", []))
    update_manifest(Path(bundle_path), C.M_METRICS, {"users": [*users, public_metrics(report, rec.id)]})
    return UserChange(Path(bundle_path), rec.id, len(new[C.M_RECORDS]), report)


def remove_user(bundle_path: Path, *, key: np.ndarray | None = None, record: str | None = None) -> UserChange:
    """`prop remove-user`: delete one user's record. Ownership is proven by the key: it must open the
    record it removes. ``record`` (an id from `prop inspect`) removes without a key, for a bundle's
    maintainer when a user lost theirs: whoever can write the files can delete a record anyway, and
    no one can add or change one without its key."""
    from .sealed import rewrite_records

    bundle = _sealed_bundle(bundle_path, "remove-user")
    if (key is None) == (record is None):
        raise PropError("remove-user needs exactly one of --key-file/--passphrase and --record", "pass one")
    ids = [e["id"] for e in bundle.manifest[C.M_RECORDS]]
    if key is not None:
        opened = bundle.sealed.open(bundle.check_key(key))
        if opened is None:
            raise PropError(
                f"the key opens no user of {bundle_path}",
                "pass the key of the user to remove, or --record ID",
            )
        record = opened.record_id
    elif record not in ids:
        raise PropError(
            f"--record {record!r} is not in {bundle_path}", "records: " + (", ".join(ids) or "none")
        )
    new = rewrite_records(Path(bundle_path), bundle.manifest, [], [record])
    return UserChange(Path(bundle_path), record, len(new[C.M_RECORDS]))
