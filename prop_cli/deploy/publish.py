"""Publishing a bundle to the Hugging Face hub (`prop push`), with a generated model card (pulling
``hf://`` checkpoints is ``prop_adapters.hub``).

`prop push` uploads an allow-list of files: the bundle's manifest and weight files, its ONNX export
if there is one, and a generated model card. Nothing else in the bundle folder (a key file someone
put there, say) is uploaded, and the card never shows key material.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from prop_adapters.hub import hub_module, is_hub_path, offline, parse_hub_path, public_name
from prop_cli import constants as C
from prop_cli.bundle import check_files, read_manifest
from prop_cli.bundle.modes import Mode, mode_of
from prop_cli.bundle.records import check_records
from prop_cli.errors import PropError, brief
from prop_cli.run.onnx import read_export

from .sign import require_signing, sign_folder, signed_note

CARD_FILE = "README.md"


def _checkpoint_label(checkpoint: str | None) -> str:
    # Format 1-3 manifests may hold a local path: only its file name goes on a public card.
    return public_name(checkpoint) or "unknown"


def _fmt(v) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


class _UnknownMode:
    """A card written without a mode (a manifest alone): its metrics as recorded."""

    @staticmethod
    def public_metrics(manifest: dict) -> dict:
        return manifest.get(C.M_METRICS, {})


def model_card(
    manifest: dict, repo_id: str, onnx_files: list[str] | None = None, mode: type[Mode] | Mode | None = None,
    signed: str | None = None,
) -> str:
    """The model card text (YAML front matter + markdown) for a bundle's manifest and mode (``mode``
    None: described as unknown). No key material."""
    hf = hub_module()
    layers = manifest.get(C.M_KEYED_LAYERS, [])
    key = manifest.get(C.M_KEY, {})
    io = manifest.get(C.M_IO, {})
    model = manifest.get(C.M_MODEL, {})
    checkpoint = io.get("checkpoint")
    data = hf.ModelCardData(
        library_name="prop-keys",
        tags=["prop", "private-personalization", "keyed-model"] + (["onnx"] if onnx_files else []),
        base_model=parse_hub_path(checkpoint).repo_id if checkpoint and is_hub_path(checkpoint) else None,
    )
    lines = [
        "---",
        data.to_yaml(),
        "---",
        "",
        f"# {repo_id.split('/')[-1]}",
        "",
        "A checkpoint personalized with prop (PRoP: private keys for neural-network "
        "checkpoints). Without the owner's secret key it behaves like the original checkpoint; with the key "
        "it behaves the owner's way. The key is not in this repository.",
        "",
        "## Model",
        "",
        f"- Base checkpoint: `{_checkpoint_label(checkpoint)}`",
        f"- Adapter: `{model.get('adapter', 'unknown')}`; task: {manifest.get(C.M_TASK, 'unknown')}; "
        f"input shape: {io.get('input_shape')}",
        f"- Mode: {mode.describe(manifest) if mode is not None else 'unknown'}",
        f"- Key: {key.get('bits')} bits"
        + (f", encoding `{key['encoding']}`" if key.get("encoding") else "")
        + f", from a {key.get('source', 'file')}; users: "
        + (str(mode.users(manifest)) if mode is not None else "unknown"),
        f"- Audit verdict: {_verdict(manifest.get(C.M_AUDIT))}",
        f"- Publisher signature: {signed or 'no (unsigned: `prop push --sign` signs every file)'}",
        f"- Bundle format {manifest.get(C.M_FORMAT)}, written by prop {manifest.get(C.M_PROP_VERSION)}",
        "",
        "| keyed layer | features |",
        "|---|---|",
        *[f"| `{x['name']}` | {x['features']} |" for x in layers],
        "",
        "## Training settings",
        "",
        "| setting | value |",
        "|---|---|",
        *[f"| {k} | {_fmt(v)} |" for k, v in sorted(manifest.get(C.M_CONFIG, {}).items())],
        "",
        "## Final metrics",
        "",
        "personalization: the owner's key on the owner's validation data (1 - mse/mse_base, or accuracy); "
        "leakage: how much of it other keys show (0 = none); fidelity: agreement with the original "
        "(mse for regression).",
        "",
        *(
            _metrics_lines(metrics)
            if (metrics := (mode or _UnknownMode).public_metrics(manifest)) is not None
            else ["Per-user figures of a sealed bundle are sealed with each user's record.", ""]
        ),
        "## Audit",
        "",
        *(
            ["```json", json.dumps(manifest[C.M_AUDIT], sort_keys=True, indent=2), "```"]
            if manifest.get(C.M_AUDIT)
            else ["No audit recorded (run `prop attack --record` before pushing to add one)."]
        ),
        "",
        "## Use",
        "",
        "```",
        f"hf download {repo_id} --local-dir bundle/",
        "prop run bundle/ --input x.npy --output y.npy                  # the original behaviour",
        "prop run bundle/ --input x.npy --key-file k.bin --output y.npy # the owner's, with the key",
        "```",
    ]
    if onnx_files:
        lines += [
            "",
            "ONNX graphs (verified against torch with onnxruntime): "
            + ", ".join(f"`onnx/{f}`" for f in onnx_files)
            + ". `base.onnx` is a drop-in for the original; the key enters `encoder.onnx` / `keyed.onnx` "
            "as its ±1 code (see `onnx/export.json`).",
        ]
    return str(hf.ModelCard("\n".join(lines) + "\n"))


def _verdict(audit: dict | None) -> str:
    if not audit:
        return "no audit recorded (`prop attack --record`)"
    gate = audit.get("max_leak")
    if not gate:
        return f"audited ({audit.get('recorded_utc')}), no --max-leak gate applied; see below"
    if gate.get("verdict"):  # prop-audit/3: the decision and its main reason, in one line
        return f"{gate['verdict']} ({audit.get('recorded_utc')})"
    failing = ", ".join(gate.get("failing", []))
    state = "**passed**" if gate.get("passed") else f"**failed** ({failing})"
    return f"{state} `--max-leak {gate.get('threshold')}` ({audit.get('recorded_utc')})"


def _metrics_lines(metrics: dict) -> list[str]:
    lines = []
    for i, u in enumerate(metrics.get("users", []), 1):
        head = f"User {i}: " + (
            f"personalization {_fmt(u['personalization'])}"
            if "personalization" in u
            else "personalization sealed"
        )
        lines += [f"{head} ({u.get('samples')} samples)", ""]
        lines += [
            "| keys | n | leakage mean | leakage worst | fidelity mean | fidelity worst |",
            "|---|---|---|---|---|---|",
        ]
        for group in ("null", "random", "hamming1"):
            g = u.get(group)
            if not g:
                continue
            lk, fd = g["leakage"], g["fidelity"]
            lines.append(
                f"| {group} | {lk['n']} | {_fmt(lk['mean'])} | {_fmt(lk['worst'])} | "
                f"{_fmt(fd['mean'])} | {_fmt(fd['worst'])} |"
            )
        lines.append("")
    return lines or ["No metrics recorded.", ""]


@dataclass
class PushResult:
    repo_id: str
    url: str
    files: list[str]
    revision: str | None


def push_bundle(
    bundle: Path,
    repo_id: str,
    *,
    private: bool = False,
    revision: str | None = None,
    onnx_dir: Path | None = None,
    token: str | None = None,
    allow_unsealed: bool = False,
    sign: Path | None = None,
    certificate: Path | None = None,
    chain: list[Path] | tuple = (),
    progress: Callable[[str], None] | None = None,
) -> PushResult:
    """Upload a verified bundle (+ its ONNX export, + a model card) to a hub model repo. Nothing the
    bundle names is imported: it is checked and copied as data.

    An unsealed bundle goes to a public repo only with ``allow_unsealed``: its encoder gives whoever
    downloads it the owner's behaviour (docs/threat-model.md). ``sign``: the publisher's private key
    (PEM; ``certificate`` and ``chain`` for certificate signing): every uploaded file is signed
    (``deploy.sign``), the card included, and ``model.sig`` is uploaded with them. ``progress(line)`` is
    told when the upload starts: after every check that can refuse (issue 28: "uploading", then a refusal)."""
    if repo_id.count("/") != 1 or not all(repo_id.split("/")):
        raise PropError(f"repo {repo_id!r} is not a hub repo id", "write <org or user>/<name>")
    hf = hub_module()
    if sign is not None:
        require_signing()  # before the bundle is read and staged
    manifest, mode = verified_files(Path(bundle))  # never publish a modified bundle; nothing is imported
    consented = private or allow_unsealed  # the user's choice, not the mode's: the mode says what is exposed
    if (exposed := mode.exposed()) is not None and not consented:
        raise PropError(
            f"{bundle} is unsealed: {exposed}",
            "personalize with --seal, push with --private, or pass --allow-unsealed to publish it anyway",
        )
    if offline():  # the client refuses at its first request: say so before staging and "uploading"
        raise PropError(f"cannot push to {repo_id}: HF_HUB_OFFLINE is set", "unset HF_HUB_OFFLINE")
    if onnx_dir is None and (Path(bundle) / C.EXPORT_DIR / C.EXPORT_META).is_file():
        onnx_dir = Path(bundle) / C.EXPORT_DIR
    onnx_files: list[str] = []
    if onnx_dir is not None:
        meta = read_export(onnx_dir, manifest)  # an export of *this* bundle, unmodified
        onnx_files = [*meta["graphs"], C.EXPORT_META]
    with tempfile.TemporaryDirectory(prefix="prop-push-") as tmp:
        stage = Path(tmp)
        names = [C.MANIFEST, *manifest[C.M_FILES], *mode.record_files(manifest)]
        for name in names:
            (stage / name).parent.mkdir(parents=True, exist_ok=True)
            _link(Path(bundle) / name, stage / name)
        if onnx_files:
            (stage / C.EXPORT_DIR).mkdir()
            for name in onnx_files:
                _link(Path(onnx_dir) / name, stage / C.EXPORT_DIR / name)
        note = signed_note(sign, certificate) if sign is not None else None
        (stage / CARD_FILE).write_text(model_card(manifest, repo_id, onnx_files[:-1], mode, note))
        if sign is not None:
            sign_folder(stage, sign, certificate, chain)
        files = sorted(str(p.relative_to(stage)) for p in stage.rglob("*") if p.is_file())
        if progress is not None:
            progress(f"uploading {bundle} to {repo_id} ({len(files)} files) ...")
        api = hf.HfApi(token=token)
        try:
            url = api.create_repo(repo_id, private=private, exist_ok=True, repo_type="model")
            if revision:
                api.create_branch(repo_id, branch=revision, exist_ok=True, repo_type="model")
            api.upload_folder(
                repo_id=repo_id,
                folder_path=str(stage),
                repo_type="model",
                revision=revision,
                commit_message=f"prop push: {Path(bundle).name}",
            )
        except hf.errors.OfflineModeIsEnabled as e:
            raise PropError(f"cannot push to {repo_id}: HF_HUB_OFFLINE is set", "unset HF_HUB_OFFLINE") from e
        except hf.errors.HfHubHTTPError as e:
            raise PropError(
                f"upload to {repo_id} failed ({str(e).splitlines()[0]})",
                "check that you are logged in (`hf auth login`) and may write to that repo",
            ) from e
        except Exception as e:  # noqa: BLE001 - OSError, and the hub client's transport errors (httpx's
            # ConnectError, timeouts), which are not OSErrors: one line, not a traceback
            raise PropError(
                f"upload to {repo_id} failed: cannot reach the hub ({brief(e)})", "check the network"
            ) from e
    return PushResult(repo_id, str(url), files, revision)


def verified_files(bundle: Path) -> tuple[dict, type[Mode]]:
    """A bundle's manifest and mode, every file checked against its sha256, without building its model
    or importing anything it names (push and verify handle bundles as data only)."""
    manifest = read_manifest(bundle)
    check_files(bundle, manifest)
    mode = mode_of(manifest)
    if mode.record_files(manifest):
        check_records(bundle, manifest)  # each record against its sha256
    return manifest, mode


def _link(src: Path, dst: Path) -> None:
    """Hard link when possible (bundles can be large), else copy."""
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)
