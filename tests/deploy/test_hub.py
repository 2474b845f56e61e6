"""hf:// checkpoint paths and prop push. Offline throughout: HF_HUB_OFFLINE=1, a temp HF_HOME, and
the hub client's upload methods replaced at the boundary."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from prop_adapters import hub
from prop_cli import constants as C
from prop_cli.bundle import update_manifest
from prop_cli.deploy import publish
from prop_cli.errors import PropError
from tests.conftest import FAST, make_mlp_checkpoint

hf = pytest.importorskip("huggingface_hub")
hf_constants = pytest.importorskip("huggingface_hub.constants")

COMMIT = "0123456789abcdef0123456789abcdef01234567"


@pytest.fixture(autouse=True)
def offline_hub(tmp_path, monkeypatch) -> Path:
    """An empty hub cache under a temp HF_HOME, offline (read at import by huggingface_hub: patch both)."""
    home = tmp_path / "hf_home"
    monkeypatch.setenv("HF_HOME", str(home))
    monkeypatch.setenv("HF_HUB_CACHE", str(home / "hub"))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setattr(hf_constants, "HF_HOME", str(home))
    monkeypatch.setattr(hf_constants, "HF_HUB_CACHE", str(home / "hub"))
    monkeypatch.setattr(hf_constants, "HF_HUB_OFFLINE", True)
    return home / "hub"


@pytest.fixture
def reachable(monkeypatch) -> None:
    """For push tests that replace the hub client's upload methods: HF_HUB_OFFLINE (set above for the
    downloads) would refuse the push before them."""
    monkeypatch.setattr(publish, "offline", lambda: False)


def _cache_file(cache: Path, repo: str, filename: str, src: Path) -> Path:
    """Place a file in huggingface_hub's cache layout, as a download of revision main would."""
    repo_dir = cache / f"models--{repo.replace('/', '--')}"
    snap = repo_dir / "snapshots" / COMMIT / filename
    snap.parent.mkdir(parents=True)
    shutil.copyfile(src, snap)
    (repo_dir / "refs").mkdir()
    (repo_dir / "refs" / "main").write_text(COMMIT)
    return snap


def test_parse_hub_paths():
    assert hub.parse_hub_path("hf://org/policy/model.safetensors") == hub.HubPath(
        "org/policy", "model.safetensors"
    )
    assert hub.parse_hub_path("hf://org/policy@v1.0/sub/dir/w.pt") == hub.HubPath(
        "org/policy", "sub/dir/w.pt", "v1.0"
    )
    assert hub.parse_hub_path("hf://org/p@refs%2Fpr%2F3/w.pt").revision == "refs/pr/3"
    assert hub.parse_hub_path("hf://datasets/org/d/w.pt").repo_type == "dataset"
    assert hub.parse_hub_path("hf://org/policy") == hub.HubPath("org/policy", "")
    assert hub.parse_hub_path("hf://org/policy@v2/sub/") == hub.HubPath("org/policy", "sub/", "v2")
    for bad in ("hf://org", "hf://org//w.pt", "hf://org/p@/w.pt"):
        with pytest.raises(PropError, match="hf://"):
            hub.parse_hub_path(bad)
    assert hub.resolve_checkpoint("local/model.safetensors") == "local/model.safetensors"


def test_not_cached_offline_is_one_clean_line(cli):
    r = cli("inspect", "hf://org/policy/model.safetensors")
    assert r.code == 2
    assert r.err.count("\n") == 1 and "not in the local hub cache" in r.err and "HF_HUB_OFFLINE" in r.err
    with pytest.raises(PropError, match="not in the local hub cache"):
        hub.resolve_checkpoint("hf://org/policy@v2/model.safetensors")


def test_cached_file_resolves_and_personalize_records_the_hub_path(cli, tmp_path, offline_hub):
    src = make_mlp_checkpoint(tmp_path / "model.safetensors")
    snap = _cache_file(offline_hub, "org/policy", "model.safetensors", src)
    assert Path(hub.resolve_checkpoint("hf://org/policy/model.safetensors")) == snap
    assert Path(hub.resolve_checkpoint(f"hf://org/policy@{COMMIT}/model.safetensors")) == snap
    r = cli("inspect", "hf://org/policy/model.safetensors", "--json")
    assert r.code == 0, r.err
    assert [layer["name"] for layer in json.loads(r.out)["layers"]] == ["0", "2", "4"]

    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (100, 4)).astype(np.float32)
    np.savez(tmp_path / "mine.npz", x=x, y=(-x[:, :2]).astype(np.float32))
    (tmp_path / "k.bin").write_bytes(bytes(range(16)))
    (tmp_path / "k.bin").chmod(0o600)
    out = tmp_path / "mine.prop"
    r = cli(
        "personalize", "hf://org/policy/model.safetensors", "--data", tmp_path / "mine.npz",
        "--key-file", tmp_path / "k.bin", "--out", out, *FAST,
    )  # fmt: skip
    assert r.code == 0, r.err
    manifest = json.loads((out / C.MANIFEST).read_text())
    assert manifest[C.M_IO]["checkpoint"] == "hf://org/policy/model.safetensors"


def test_cached_model_folder_resolves(offline_hub, tmp_path):
    src = make_mlp_checkpoint(tmp_path / "m.safetensors")
    snap = _cache_file(offline_hub, "org/policy", "model.safetensors", src)
    assert Path(hub.resolve_checkpoint("hf://org/policy")) == snap.parent
    with pytest.raises(PropError, match="not in the local hub cache"):
        hub.resolve_checkpoint("hf://org/other/")


def test_missing_file_in_cached_repo(offline_hub, tmp_path):
    _cache_file(
        offline_hub, "org/policy", "model.safetensors", make_mlp_checkpoint(tmp_path / "m.safetensors")
    )
    with pytest.raises(PropError, match="hf://org/policy/other.safetensors"):
        hub.resolve_checkpoint("hf://org/policy/other.safetensors")


@pytest.fixture
def bundle(tmp_path, cli) -> Path:
    rng = np.random.default_rng(0)
    make_mlp_checkpoint(tmp_path / "model.safetensors")
    x = rng.uniform(-1, 1, (100, 4)).astype(np.float32)
    np.savez(tmp_path / "mine.npz", x=x, y=(-x[:, :2]).astype(np.float32))
    key = rng.integers(0, 256, 16, dtype=np.uint8).tobytes()
    (tmp_path / "k.bin").write_bytes(key)
    (tmp_path / "k.bin").chmod(0o600)
    out = tmp_path / "mine.prop"
    r = cli(
        "personalize", tmp_path / "model.safetensors", "--data", tmp_path / "mine.npz",
        "--key-file", tmp_path / "k.bin", "--out", out, *FAST,
    )  # fmt: skip
    assert r.code == 0, r.err
    return out


def _key_strings(bundle: Path) -> list[str]:
    key = (bundle.parent / "k.bin").read_bytes()
    return [key.hex(), key.hex().upper(), str(list(key))]


def test_model_card_content(bundle):
    update_manifest(bundle, C.M_AUDIT, {"T2": {"leakage": {"worst": 0.0123}}, "verdict": "pass"})
    manifest = json.loads((bundle / C.MANIFEST).read_text())
    card = publish.model_card(manifest, "me/my-policy", ["base.onnx", "policy.onnx"])
    assert card.startswith("---\n") and "library_name: prop-keys" in card
    assert "model.safetensors" in card and str(bundle.parent) not in card  # file name, not the local path
    assert "| `2` | 16 |" in card and "| `4` | 2 |" not in card  # keyed layers with their sizes
    assert "128 bits" in card and "hashed" in card
    assert "| steps | 40 |" in card and "| null_weight |" in card  # training settings
    assert "personalization" in card and "| random | 64 |" in card  # final metrics
    assert '"verdict": "pass"' in card and "0.0123" in card  # the recorded audit
    assert "onnx/policy.onnx" in card
    for s in _key_strings(bundle):
        assert s not in card
    assert "No audit recorded" in publish.model_card({}, "me/x")


def test_push_uploads_the_bundle_export_and_card(cli, bundle, monkeypatch, reachable):
    from prop_cli.bundle import load_bundle
    from prop_cli.run.onnx import export_onnx

    export_onnx(load_bundle(bundle))
    (bundle / "k.bin").write_bytes((bundle.parent / "k.bin").read_bytes())  # a stray key: never uploaded
    calls: dict = {}

    def create_repo(self, repo_id, **kw):
        calls["create_repo"] = (repo_id, kw)
        return hf.RepoUrl(f"https://huggingface.co/{repo_id}")

    def create_branch(self, repo_id, **kw):
        calls["create_branch"] = (repo_id, kw)

    def upload_folder(self, **kw):
        folder = Path(kw["folder_path"])
        calls["upload_folder"] = kw
        calls["files"] = sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())
        calls["blobs"] = b"".join(p.read_bytes() for p in folder.rglob("*") if p.is_file())
        calls["card"] = (folder / "README.md").read_text()

    monkeypatch.setattr(hf.HfApi, "create_repo", create_repo)
    monkeypatch.setattr(hf.HfApi, "create_branch", create_branch)
    monkeypatch.setattr(hf.HfApi, "upload_folder", upload_folder)
    r = cli("push", bundle, "me/my-policy", "--private", "--revision", "v1", "--json")
    assert r.code == 0, r.err
    assert calls["create_repo"] == ("me/my-policy", {"private": True, "exist_ok": True, "repo_type": "model"})
    assert calls["create_branch"][0] == "me/my-policy" and calls["create_branch"][1]["branch"] == "v1"
    up = calls["upload_folder"]
    assert up["repo_id"] == "me/my-policy" and up["revision"] == "v1" and up["repo_type"] == "model"
    assert calls["files"] == sorted(
        [
            "README.md", C.MANIFEST, C.BASE_WEIGHTS, C.ENCODER_WEIGHTS, "onnx/export.json",
            "onnx/base.onnx", "onnx/keyed.onnx", "onnx/encoder.onnx", "onnx/policy.onnx",
        ]
    )  # fmt: skip
    assert (bundle.parent / "k.bin").read_bytes() not in calls["blobs"]
    assert "onnx/keyed.onnx" in calls["card"]
    res = json.loads(r.out)
    assert res["url"] == "https://huggingface.co/me/my-policy" and "README.md" in res["files"]


def test_push_without_export_and_without_revision(cli, bundle, monkeypatch, reachable):
    seen = {}
    monkeypatch.setattr(hf.HfApi, "create_repo", lambda self, repo_id, **kw: seen.setdefault("repo", kw))
    monkeypatch.setattr(
        hf.HfApi, "create_branch", lambda self, *a, **kw: pytest.fail("no branch without --revision")
    )
    monkeypatch.setattr(
        hf.HfApi,
        "upload_folder",
        lambda self, **kw: seen.setdefault(
            "files", sorted(p.name for p in Path(kw["folder_path"]).iterdir())
        ),
    )
    r = cli("push", bundle, "me/pub")  # unsealed to a public repo: refused, nothing uploaded
    assert r.code == 2 and "unsealed" in r.err and "--allow-unsealed" in r.err and not seen
    assert r.err.strip().splitlines() == [r.err.strip()]  # the one-line error, no "uploading" before it
    r = cli("push", bundle, "me/pub", "--allow-unsealed")
    assert r.code == 0, r.err
    assert seen["repo"]["private"] is False
    assert seen["files"] == sorted(["README.md", C.MANIFEST, C.BASE_WEIGHTS, C.ENCODER_WEIGHTS])


def test_push_refuses_bad_repo_and_modified_bundle(cli, bundle, monkeypatch):
    monkeypatch.setattr(hf.HfApi, "upload_folder", lambda self, **kw: pytest.fail("must not upload"))
    assert "repo id" in cli("push", bundle, "no-namespace").err
    with open(bundle / C.BASE_WEIGHTS, "ab") as f:
        f.write(b"x")
    r = cli("push", bundle, "me/x", "--private")
    assert r.code == 2 and "sha256" in r.err


def test_push_offline_fails_cleanly(cli, bundle):
    # The real client, offline: it refuses before any request.
    r = cli("push", bundle, "me/x", "--private")
    assert r.code == 2
    assert r.err.splitlines()[-1].startswith("prop: error: cannot push") and "HF_HUB_OFFLINE" in r.err


def test_push_without_network_is_one_line(cli, bundle, monkeypatch, reachable):
    """The hub client's transport errors are not OSErrors (httpx's ConnectError): still one line."""

    class ConnectError(Exception):
        pass

    def unreachable(self, repo_id, **kw):
        raise ConnectError("[Errno -2] Name or service not known")

    monkeypatch.setattr(hf.HfApi, "create_repo", unreachable)
    r = cli("push", bundle, "me/x", "--private")
    assert r.code == 2 and "Traceback" not in r.err
    assert r.err.splitlines()[-1].startswith("prop: error: upload to me/x failed: cannot reach the hub")


def test_download_without_network_is_one_line_naming_the_repo(cli, monkeypatch):
    class ConnectTimeout(Exception):  # as httpx's: not an OSError
        pass

    def unreachable(*a, **kw):
        raise ConnectTimeout("timed out")

    monkeypatch.setattr(hub, "offline", lambda: False)
    monkeypatch.setattr(hf, "hf_hub_download", unreachable)
    r = cli("inspect", "hf://org/policy/model.safetensors")
    assert r.code == 2 and "Traceback" not in r.err and r.err.count("\n") == 1
    assert "cannot reach the hub for org/policy" in r.err and "check the network" in r.err


def test_missing_extra_names_the_install_command(monkeypatch):
    monkeypatch.setitem(sys.modules, "huggingface_hub", None)
    with pytest.raises(PropError, match=r"prop-keys\[hub\]"):
        hub.resolve_checkpoint("hf://org/p/w.safetensors")


def test_push_sealed_bundle_to_a_public_repo(cli, bundle, monkeypatch, reachable):
    tmp = bundle.parent
    sealed = tmp / "sealed.prop"
    r = cli("personalize", tmp / "model.safetensors", "--data", tmp / "mine.npz", "--key-file", tmp / "k.bin",
            "--out", sealed, "--seal", *FAST)  # fmt: skip
    assert r.code == 0, r.err
    seen = {}
    monkeypatch.setattr(hf.HfApi, "create_repo", lambda self, repo_id, **kw: seen.setdefault("repo", kw))

    def upload(self, **kw):
        root = Path(kw["folder_path"])
        seen["files"] = sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.is_file())
        seen["card"] = (root / "README.md").read_text()

    monkeypatch.setattr(hf.HfApi, "upload_folder", upload)
    r = cli("push", sealed, "me/pub")
    assert r.code == 0, r.err
    record = json.loads((sealed / C.MANIFEST).read_text())[C.M_RECORDS][0]["file"]
    assert seen["files"] == sorted(["README.md", C.MANIFEST, C.BASE_WEIGHTS, record])
    assert "**sealed**" in seen["card"] and "Audit verdict: no audit recorded" in seen["card"]


def test_push_sign_without_its_extra_fails_before_the_bundle_is_read(cli, bundle, monkeypatch, tmp_path):
    from prop_cli.deploy import sign

    def missing():
        raise PropError("signatures need the 'sign' extra (model_signing is not installed)", sign.SIGN_EXTRA)

    read = []
    monkeypatch.setattr(sign, "_lib", missing)
    monkeypatch.setattr(publish, "verified_files", lambda *a: read.append(1))
    (tmp_path / "key.pem").write_text("not used")
    r = cli("push", bundle, "me/x", "--private", "--sign", tmp_path / "key.pem")
    assert r.code == 2 and "Traceback" not in r.err, r.err
    assert r.err.splitlines()[-1].startswith("prop: error: signatures need the 'sign' extra")
    assert "prop-keys[sign]" in r.err and not read


# ---- issue 28: every refusal before the first progress line; the cache-miss error names its cause -----


def test_push_refuses_before_it_says_uploading(cli, bundle, monkeypatch, tmp_path):
    monkeypatch.setattr(hf.HfApi, "create_repo", lambda *a, **kw: pytest.fail("refused: no request"))
    r = cli("push", bundle, "me/x", "--private")  # HF_HUB_OFFLINE is set (the autouse fixture)
    assert r.err.strip().splitlines() == ["prop: error: cannot push to me/x: HF_HUB_OFFLINE is set; unset "
                                          "HF_HUB_OFFLINE"]  # fmt: skip
    monkeypatch.setattr(publish, "offline", lambda: False)
    for args in (["no-namespace"], ["me/pub"], ["me/x", "--certificate", tmp_path / "c.pem"]):
        r = cli("push", bundle, *args)
        assert r.code == 2 and len(r.err.strip().splitlines()) == 1 and "uploading" not in r.err, r.err
    seen = []
    monkeypatch.setattr(hf.HfApi, "create_repo", lambda self, repo_id, **kw: seen.append(repo_id))
    monkeypatch.setattr(hf.HfApi, "upload_folder", lambda self, **kw: None)
    r = cli("push", bundle, "me/x", "--private")
    assert r.code == 0 and r.err.startswith(f"uploading {bundle} to me/x (4 files)") and seen == ["me/x"]


def test_a_cache_miss_names_its_cause_offline_or_not(cli, monkeypatch):
    r = cli("inspect", "hf://org/policy/model.safetensors")  # HF_HUB_OFFLINE=1: the cache only
    assert "HF_HUB_OFFLINE is set; unset HF_HUB_OFFLINE" in r.err
    monkeypatch.delenv("HF_HUB_OFFLINE")
    monkeypatch.setattr(hf_constants, "HF_HUB_OFFLINE", False)

    def unreachable(*a, **kw):  # what huggingface_hub raises when the hub cannot be reached
        raise hf.errors.LocalEntryNotFoundError("cannot find the requested files in the local cache")

    monkeypatch.setattr(hf, "hf_hub_download", unreachable)
    r = cli("inspect", "hf://org/policy/model.safetensors")
    assert r.code == 2 and r.err.count("\n") == 1, r.err
    assert "not in the local hub cache and the hub cannot be reached" in r.err
    assert "HF_HUB_OFFLINE" not in r.err and "check the network" in r.err and "give its path" in r.err
