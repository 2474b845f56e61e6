"""The Hugging Face hub, pulling: ``hf://`` checkpoint paths (publishing is ``prop_cli.deploy.publish``).

``hf://<org>/<name>[@revision]/<path/in/repo>`` (``hf://datasets/<org>/<name>/...`` for a dataset
repo) is fetched with ``huggingface_hub.hf_hub_download`` into the usual hub cache; a path ending in
"/" (or the bare ``hf://<org>/<name>``) is a model folder, fetched with ``snapshot_download``
(its *.json and *.safetensors only). With
``HF_HUB_OFFLINE=1`` only the cache is used. A revision containing "/" is URL-encoded
(``refs%2Fpr%2F1``), as in huggingface_hub's own ``hf://`` paths.

huggingface_hub is imported inside the functions: it is an optional extra (``prop-keys[hub]``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import unquote

from prop_cli.errors import PropError, brief

HF_SCHEME = "hf://"
HUB_EXTRA = "pip install 'prop-keys[hub]'"


@dataclass(frozen=True)
class HubPath:
    repo_id: str
    filename: str
    revision: str | None = None
    repo_type: str = "model"


def is_hub_path(path: str | Path) -> bool:
    return str(path).startswith(HF_SCHEME)


def public_name(path: str | Path | None) -> str | None:
    """How a bundle names the checkpoint it came from: a hub path as given, a local one by its file name
    only (a local path may carry a user name, and a bundle is shared)."""
    if not path:
        return None
    if is_hub_path(path):
        return str(path)
    return str(path).rstrip("/\\").replace("\\", "/").split("/")[-1] or None


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


def hub_module():
    try:
        import huggingface_hub
        import huggingface_hub.constants  # lazy package: submodules become attributes once imported
        import huggingface_hub.errors
    except ImportError as e:
        raise PropError("hf:// paths and prop push need the 'hub' extra (huggingface_hub)", HUB_EXTRA) from e
    return huggingface_hub


def offline() -> bool:
    """Whether HF_HUB_OFFLINE is set (the hub client then uses only its cache, and refuses uploads)."""
    # huggingface_hub reads HF_HUB_OFFLINE once, at import; read it again so a change is honoured.
    env = os.environ.get("HF_HUB_OFFLINE", "").strip().lower() in {"1", "true", "yes", "on"}
    return env or bool(hub_module().constants.HF_HUB_OFFLINE)


def resolve_checkpoint(path: str | Path) -> str | Path:
    """A local path for a checkpoint argument: ``hf://`` paths are downloaded (or found in the cache)."""
    if not is_hub_path(path):
        return path
    hp = parse_hub_path(str(path))
    hf = hub_module()
    cache_only = offline()
    common = {"revision": hp.revision, "repo_type": hp.repo_type, "local_files_only": cache_only}
    try:
        if hp.filename == "" or hp.filename.endswith("/"):
            # A model folder: fetch its configs and weights, not everything in the repo.
            patterns = [hp.filename + p for p in ("*.json", "*.safetensors")]
            root = hf.snapshot_download(
                hp.repo_id, allow_patterns=patterns, library_name="prop-keys", **common
            )
            return str(Path(root) / hp.filename)
        return hf.hf_hub_download(hp.repo_id, hp.filename, library_name="prop-keys", **common)
    except Exception as e:  # noqa: BLE001 - mapped to one line below, anything else re-raised
        raise _download_error(e, path, hp, cache_only) from e


def _download_error(e: Exception, path: str | Path, hp: HubPath, cache_only: bool) -> PropError:
    """The one-line error for a failed download (most specific huggingface_hub error first)."""
    errors = hub_module().errors
    first_line = str(e).splitlines()[0] if str(e).strip() else type(e).__name__
    # Not in the cache: the fix depends on why the hub was not asked (issue 28: "unset HF_HUB_OFFLINE"
    # was the fix given when it was not set, and the network was the cause).
    if cache_only:
        why, fix = "HF_HUB_OFFLINE is set", "unset HF_HUB_OFFLINE to download it"
    else:
        why = "the hub cannot be reached"
        fix = "check the network, or download the checkpoint where the hub is reachable and give its path"
    cases = [
        (errors.LocalEntryNotFoundError, f"{path} is not in the local hub cache and {why}", fix),
        (
            errors.GatedRepoError,
            f"{path}: repo {hp.repo_id} is gated",
            "accept its terms on the hub and log in",
        ),
        (
            errors.RepositoryNotFoundError,
            f"{path}: repo {hp.repo_id} not found (or private)",
            "check the name, or log in with `hf auth login` for a private repo",
        ),
        (
            errors.RevisionNotFoundError,
            f"{path}: revision {hp.revision} not found",
            "check the branch, tag or commit",
        ),
        (
            errors.EntryNotFoundError,
            f"{path}: no file {hp.filename} in {hp.repo_id}",
            "check the path inside the repo",
        ),
        (errors.HfHubHTTPError, f"{path}: the hub answered with an error ({first_line})", "try again"),
        (OSError, f"{path}: cannot reach the hub for {hp.repo_id} ({type(e).__name__})", "check the network"),
    ]
    for cls, what, fix in cases:
        if isinstance(e, cls):
            return PropError(what, fix)
    # The hub client's transport errors (httpx's ConnectError, timeouts) are not OSErrors.
    return PropError(
        f"{path}: cannot reach the hub for {hp.repo_id} ({brief(e)})",
        "check the network; HF_HUB_OFFLINE=1 uses only the local cache",
    )
