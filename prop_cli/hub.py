"""The Hugging Face hub: ``hf://`` checkpoint paths and `prop push`.

``hf://<org>/<name>[@revision]/<path/in/repo>`` (``hf://datasets/<org>/<name>/...`` for a dataset
repo) is fetched with ``huggingface_hub.hf_hub_download`` into the usual hub cache; a path ending in
"/" (or the bare ``hf://<org>/<name>``) is a model folder, fetched with ``snapshot_download``
(its *.json and *.safetensors only). With
``HF_HUB_OFFLINE=1`` only the cache is used. A revision containing "/" is URL-encoded
(``refs%2Fpr%2F1``), as in huggingface_hub's own ``hf://`` paths.

`prop push` uploads an allow-list of files: the bundle's manifest and weight files, its ONNX export
if there is one, and a generated model card. Nothing else in the bundle folder (a key file someone
put there, say) is uploaded, and the card never shows key material.

huggingface_hub is imported inside the functions: it is an optional extra (``prop-cli[hub]``).
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import unquote

from . import constants as C
from .errors import PropError

HF_SCHEME = "hf://"
HUB_EXTRA = "pip install 'prop-cli[hub]'"
CARD_FILE = "README.md"


@dataclass(frozen=True)
class HubPath:
    repo_id: str
    filename: str
    revision: str | None = None
    repo_type: str = "model"


def is_hub_path(path: str | Path) -> bool:
    return str(path).startswith(HF_SCHEME)


def parse_hub_path(path: str) -> HubPath:
    """Split ``hf://[datasets/]org/name[@rev][/path]`` into its parts; a PropError if malformed.

    A path ending in "/" (or none) names a folder (e.g. a config.json + model.safetensors layout):
    ``filename`` then ends in "/" ("" for the repo root).
    """
    rest = str(path)[len(HF_SCHEME) :]
    repo_type = "model"
    if rest.startswith("datasets/"):
        repo_type, rest = "dataset", rest[len("datasets/") :]
    is_folder = rest.endswith("/") or rest.count("/") == 1
    parts = rest.rstrip("/").split("/")
    if len(parts) < 2 or not all(parts):
        raise PropError(
            f"{path} is not a hub path",
            "write hf://<org>/<name>[@revision]/<file>, e.g. hf://org/policy/model.safetensors",
        )
    org, name = parts[0], parts[1]
    revision = None
    if "@" in name:
        name, revision = name.split("@", 1)
        revision = unquote(revision)
        if not name or not revision:
            raise PropError(
                f"{path}: empty repo name or revision", "write hf://<org>/<name>@<revision>/<file>"
            )
    filename = "/".join(parts[2:]) + ("/" if is_folder and len(parts) > 2 else "")
    return HubPath(f"{org}/{name}", filename, revision, repo_type)


def _hf():
    try:
        import huggingface_hub
        import huggingface_hub.constants  # lazy package: submodules become attributes once imported
        import huggingface_hub.errors
    except ImportError as e:
        raise PropError("hf:// paths and prop push need the 'hub' extra (huggingface_hub)", HUB_EXTRA) from e
    return huggingface_hub


def _offline() -> bool:
    # huggingface_hub reads HF_HUB_OFFLINE once, at import; read it again so a change is honoured.
    env = os.environ.get("HF_HUB_OFFLINE", "").strip().lower() in {"1", "true", "yes", "on"}
    return env or bool(_hf().constants.HF_HUB_OFFLINE)


def resolve_checkpoint(path: str | Path) -> str | Path:
    """A local path for a checkpoint argument: ``hf://`` paths are downloaded (or found in the cache)."""
    if not is_hub_path(path):
        return path
    hp = parse_hub_path(str(path))
    hf = _hf()
    errors = hf.errors
    offline = _offline()
    common = {"revision": hp.revision, "repo_type": hp.repo_type, "local_files_only": offline}
    try:
        if hp.filename == "" or hp.filename.endswith("/"):
            # A model folder: fetch its configs and weights, not everything in the repo.
            patterns = [hp.filename + p for p in ("*.json", "*.safetensors")]
            root = hf.snapshot_download(
                hp.repo_id, allow_patterns=patterns, library_name="prop-cli", **common
            )
            return str(Path(root) / hp.filename)
        return hf.hf_hub_download(hp.repo_id, hp.filename, library_name="prop-cli", **common)
    except errors.LocalEntryNotFoundError as e:
        why = "HF_HUB_OFFLINE is set" if offline else "the hub cannot be reached"
        raise PropError(
            f"{path} is not in the local hub cache and {why}",
            "connect to the network (unset HF_HUB_OFFLINE), or download it once while online",
        ) from e
    except errors.GatedRepoError as e:
        raise PropError(
            f"{path}: repo {hp.repo_id} is gated", "accept its terms on the hub and log in"
        ) from e
    except errors.RepositoryNotFoundError as e:
        raise PropError(
            f"{path}: repo {hp.repo_id} not found (or private)",
            "check the name, or log in with `hf auth login` for a private repo",
        ) from e
    except errors.RevisionNotFoundError as e:
        raise PropError(f"{path}: revision {hp.revision} not found", "check the branch, tag or commit") from e
    except errors.EntryNotFoundError as e:
        raise PropError(
            f"{path}: no file {hp.filename} in {hp.repo_id}", "check the path inside the repo"
        ) from e
    except errors.HfHubHTTPError as e:
        raise PropError(
            f"{path}: the hub answered with an error ({str(e).splitlines()[0]})", "try again"
        ) from e
    except OSError as e:  # connection errors
        raise PropError(f"{path}: cannot reach the hub ({type(e).__name__})", "check the network") from e


def _checkpoint_label(checkpoint: str | None) -> str:
    if not checkpoint:
        return "unknown"
    # A local path may carry a user name; only its file name goes on a public card.
    return checkpoint if is_hub_path(checkpoint) else Path(checkpoint).name


def _fmt(v) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def model_card(manifest: dict, repo_id: str, onnx_files: list[str] | None = None) -> str:
    """The model card text (YAML front matter + markdown) for a bundle's manifest. No key material."""
    hf = _hf()
    layers = manifest.get(C.M_KEYED_LAYERS, [])
    key = manifest.get(C.M_KEY, {})
    io = manifest.get(C.M_IO, {})
    model = manifest.get(C.M_MODEL, {})
    checkpoint = io.get("checkpoint")
    data = hf.ModelCardData(
        library_name="prop-cli",
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
        f"- Key: {key.get('bits')} bits, encoding `{key.get('encoding')}`, "
        f"from a {key.get('source', 'file')}; users: {key.get('users', 1)}",
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
        *_metrics_lines(manifest.get(C.M_METRICS, {})),
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


def _metrics_lines(metrics: dict) -> list[str]:
    lines = []
    for i, u in enumerate(metrics.get("users", []), 1):
        lines += [
            f"User {i}: personalization {_fmt(u.get('personalization'))} ({u.get('samples')} samples)",
            "",
        ]
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
) -> PushResult:
    """Upload a verified bundle (+ its ONNX export, + a model card) to a hub model repo."""
    from .bundle import load_bundle
    from .export import EXPORT_DIR, EXPORT_META, read_export

    if repo_id.count("/") != 1 or not all(repo_id.split("/")):
        raise PropError(f"repo {repo_id!r} is not a hub repo id", "write <org or user>/<name>")
    hf = _hf()
    b = load_bundle(bundle)  # verifies the hashes: never publish a modified bundle
    manifest = b.manifest
    if onnx_dir is None and (Path(bundle) / EXPORT_DIR / EXPORT_META).is_file():
        onnx_dir = Path(bundle) / EXPORT_DIR
    onnx_files: list[str] = []
    if onnx_dir is not None:
        meta = read_export(onnx_dir, manifest)  # an export of *this* bundle, unmodified
        onnx_files = [*meta["graphs"], EXPORT_META]
    with tempfile.TemporaryDirectory(prefix="prop-push-") as tmp:
        stage = Path(tmp)
        names = [C.MANIFEST, *manifest[C.M_FILES]]
        for name in names:
            _link(Path(bundle) / name, stage / name)
        if onnx_files:
            (stage / EXPORT_DIR).mkdir()
            for name in onnx_files:
                _link(Path(onnx_dir) / name, stage / EXPORT_DIR / name)
        (stage / CARD_FILE).write_text(model_card(manifest, repo_id, onnx_files[:-1]))
        files = sorted(str(p.relative_to(stage)) for p in stage.rglob("*") if p.is_file())
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
        except OSError as e:
            raise PropError(
                f"upload to {repo_id} failed: cannot reach the hub ({type(e).__name__})", "check the network"
            ) from e
    return PushResult(repo_id, str(url), files, revision)


def _link(src: Path, dst: Path) -> None:
    """Hard link when possible (bundles can be large), else copy."""
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)
