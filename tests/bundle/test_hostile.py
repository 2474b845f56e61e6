"""Bundles written by an attacker, the way an attacker would (every digest recomputed with prop's own
public functions): code a file names never runs without --trust-remote-code, and a user's key runs
only what its holder enrolled. Each plant ends in a marker file that never appears, or a refusal (exit 2,
one line); a key enrolled in nothing is refused too, and runs the bundle's base exactly, with a warning,
only with --allow-unenrolled-key."""

from __future__ import annotations

import json
import shutil
import uuid
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from prop_cli import constants as C
from prop_cli.api import (
    KeySource,
    PersonalizeConfig,
    load_bundle,
    personalize_checkpoint,
    read_key_file,
    run_bundle,
)
from prop_cli.bundle.manifest import stamp
from prop_cli.errors import PropError
from prop_cli.files import dump_json, sha256_file
from prop_cli.run.policy import KeyedPolicy, WrongKeyWarning
from tests.conftest import make_mlp_checkpoint

ort = pytest.importorskip("onnxruntime")


def _bundle(root: Path, name: str, seal: bool, key: str = "k.bin", seed: int = 0, ckpt_seed: int = 0) -> Path:
    ckpt = root / f"model{ckpt_seed}.safetensors"
    if not ckpt.exists():
        make_mlp_checkpoint(ckpt, seed=ckpt_seed)
    cfg = PersonalizeConfig.of(steps=150 if seal else 80, seed=seed, seal=seal)
    bits = read_key_file(root / key)
    personalize_checkpoint(str(ckpt), [(root / "mine.npz", KeySource(bits, "file"))], root / name, cfg)
    return root / name


@pytest.fixture(scope="module")
def made(tmp_path_factory) -> Path:
    """The user's unsealed and sealed bundles (key k.bin), and an attacker's own bundle (key a.bin) of
    another checkpoint: the raw material of every plant."""
    root = tmp_path_factory.mktemp("hostile")
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (200, 4)).astype(np.float32)
    np.savez(root / "mine.npz", x=x, y=(-x[:, :2] * 0.5).astype(np.float32))
    np.save(root / "x.npy", x[:16])
    for name in ("k.bin", "a.bin"):
        (root / name).write_bytes(rng.integers(0, 256, 16, dtype=np.uint8).tobytes())
        (root / name).chmod(0o600)
    _bundle(root, "user.prop", seal=False)
    _bundle(root, "sealed.prop", seal=True)
    _bundle(root, "attacker.prop", seal=False, key="a.bin", seed=1, ckpt_seed=1)
    return root


@pytest.fixture
def d(made, tmp_path) -> Path:
    """A fresh copy of the material for one test to plant in."""
    shutil.copytree(made, tmp_path / "w")
    return tmp_path / "w"


def _manifest(bundle: Path) -> dict:
    return json.loads((bundle / C.MANIFEST).read_text())


def _write(bundle: Path, m: dict) -> None:
    """What an attacker does after an edit: every listed file's sha256 and the manifest digest again."""
    m[C.M_FILES] = {name: sha256_file(bundle / name) for name in m[C.M_FILES]}
    (bundle / C.MANIFEST).write_text(dump_json(stamp(m)))


def _base(bundle: Path, x: np.ndarray) -> np.ndarray:
    b = load_bundle(bundle)
    with torch.no_grad():
        return b.loaded.module(torch.from_numpy(x)).numpy()


def _run(cli, bundle: Path, d: Path, *extra) -> tuple[int, np.ndarray | None, str]:
    out = d / f"y-{uuid.uuid4().hex[:6]}.npy"
    r = cli("run", bundle, "--input", d / "x.npy", "--output", out, *extra)
    return r.code, (np.load(out) if out.exists() else None), r.err


def _one_line_refusal(code: int, y, err: str, *words: str) -> None:
    assert code == 2 and y is None, err
    assert err.count("\n") == 1 and err.startswith("prop: error:"), err
    for w in words:
        assert w in err, err


# ---- 1. code a file names ---------------------------------------------------------------------


def _hostile_code(bundle: Path, d: Path, adapter: str, marker: Path, monkeypatch) -> None:
    """model.arch names code: os:system with the command in arch_kwargs (module adapter), or a module
    planted where prop used to look (the working directory) that acts on import (folder adapter)."""
    m = _manifest(bundle)
    if adapter == "module":
        kwargs = {"command": f"touch {marker}"}
        m[C.M_MODEL] = {"adapter": "module", "arch": "os:system", "arch_kwargs": kwargs}
    else:
        name = f"pwn_{uuid.uuid4().hex[:8]}"
        (d / f"{name}.py").write_text(f"open({str(marker)!r}, 'w').close()\ndef build(config): return 1\n")
        monkeypatch.chdir(d)
        m[C.M_MODEL] = {"adapter": "folder", "arch": f"{name}:build", "arch_kwargs": {}, "builder": "--arch",
                        "config": {"type": "x"}}  # fmt: skip
    _write(bundle, m)


@pytest.mark.parametrize("adapter", ["module", "folder"])
@pytest.mark.parametrize("mode", ["user.prop", "sealed.prop"])
def test_no_command_imports_what_a_bundle_names(cli, d, mode, adapter, monkeypatch):
    marker = d / "pwned"
    bundle = d / mode
    _hostile_code(bundle, d, adapter, marker, monkeypatch)
    calls = [
        ("run", bundle, "--input", d / "x.npy", "--output", d / "y.npy"),
        ("run", bundle, "--input", d / "x.npy", "--output", d / "y.npy", "--key-file", d / "k.bin"),
        ("run", bundle, "--input", d / "x.npy", "--output", d / "y.npy", "--onnx"),
        ("attack", bundle, "--data", d / "mine.npz", "--probes", "null"),
        ("export", bundle, "--onnx"),
        ("eval", bundle, "--env", "CartPole-v1"),
        ("remove-user", bundle, "--record", "x"),
        ("add-user", bundle, "--data", d / "mine.npz", "--key-file", d / "a.bin"),
    ]
    for args in calls:
        r = cli(*args)
        _one_line_refusal(r.code, None, r.err, "names code to import and run", "--trust-remote-code")
        assert not marker.exists(), args
    with pytest.raises(PropError, match="--trust-remote-code"):
        load_bundle(bundle)
    assert not marker.exists()
    # The test is live: with the user's consent the named code does run.
    r = cli("run", bundle, "--input", d / "x.npy", "--output", d / "y.npy", "--trust-remote-code")
    assert r.code == 2 and marker.exists(), r.err


def test_push_and_enrol_handle_a_hostile_bundle_as_data(cli, d, monkeypatch):
    hf = pytest.importorskip("huggingface_hub")
    marker = d / "pwned"
    _hostile_code(d / "user.prop", d, "module", marker, monkeypatch)
    url = lambda self, repo_id, **kw: hf.RepoUrl(f"https://huggingface.co/{repo_id}")  # noqa: E731
    monkeypatch.setattr(hf.HfApi, "create_repo", url)
    monkeypatch.setattr(hf.HfApi, "upload_folder", lambda self, **kw: None)
    r = cli("push", d / "user.prop", "me/x", "--private")
    assert r.code == 0 and not marker.exists(), r.err
    # Enrolling is consent to run what the bundle runs: refused as run refuses it (issue 31: it exited
    # 0 without a word); with the flag it enrols, and still imports nothing.
    r = cli("enrol", d / "user.prop", "--key-file", d / "a.bin")
    _one_line_refusal(r.code, None, r.err, "names code to import and run", "os:system", "--trust-remote-code")
    assert not marker.exists() and "enrolments" in _manifest(d / "user.prop")
    before = len(_manifest(d / "user.prop")[C.M_ENROLMENTS])
    r = cli("enrol", d / "user.prop", "--key-file", d / "a.bin", "--trust-remote-code")
    assert r.code == 0 and not marker.exists(), r.err
    assert len(_manifest(d / "user.prop")[C.M_ENROLMENTS]) == before + 1


# ---- 2. a key runs only what its holder enrolled ----------------------------------------------

ALLOW = "--allow-unenrolled-key"


def _not_enrolled(code: int, y, err: str, bundle: Path) -> None:
    """The refusal of a key that opens nothing (issue 31): one line naming the bundle and the option."""
    _one_line_refusal(code, y, err, f"the key is enrolled in nothing in {bundle}", "may have been replaced",
                      "the user removed", ALLOW)  # fmt: skip


@pytest.mark.parametrize("mode", ["user.prop", "sealed.prop"])
def test_a_key_enrolled_in_nothing_is_refused_and_allowed_runs_the_base_exactly(cli, d, mode):
    bundle = d / mode
    x = np.load(d / "x.npy")
    code, y_none, _ = _run(cli, bundle, d)
    assert code == 0
    _not_enrolled(*_run(cli, bundle, d, "--key-file", d / "a.bin"), bundle)
    code, y_wrong, err = _run(cli, bundle, d, "--key-file", d / "a.bin", ALLOW)
    assert code == 0
    np.testing.assert_array_equal(y_wrong, y_none)
    np.testing.assert_array_equal(y_none, _base(bundle, x))
    assert "enrolled in nothing" in err and "the bundle's base" in err and "original" not in err
    code, y_user, _ = _run(cli, bundle, d, "--key-file", d / "k.bin")
    assert code == 0 and np.abs(y_user - y_none).max() > 1e-3  # the enrolled key: its behaviour
    b = load_bundle(bundle)
    with pytest.raises(PropError, match="enrolled in nothing"):
        KeyedPolicy(b, read_key_file(d / "a.bin"))
    with pytest.raises(PropError, match="enrolled in nothing"):
        run_bundle(b, x, read_key_file(d / "a.bin"))
    with pytest.warns(WrongKeyWarning, match="enrolled in nothing"):
        np.testing.assert_array_equal(KeyedPolicy(b, read_key_file(d / "a.bin"), allow_unenrolled=True)(x),
                                      y_none)  # fmt: skip
    # ONNX: the export binds the user's key; another key is refused, and allowed runs base.onnx exactly.
    assert cli("export", bundle, "--onnx", "--key-file", d / "k.bin").code == 0
    code, o_none, _ = _run(cli, bundle, d, "--onnx")
    _not_enrolled(*_run(cli, bundle, d, "--onnx", "--key-file", d / "a.bin"), bundle)
    code2, o_wrong, err = _run(cli, bundle, d, "--onnx", "--key-file", d / "a.bin", ALLOW)
    assert code == code2 == 0 and "enrolled in nothing" in err, err
    np.testing.assert_array_equal(o_wrong, o_none)
    code, o_user, _ = _run(cli, bundle, d, "--onnx", "--key-file", d / "k.bin")
    np.testing.assert_allclose(o_user, y_user, atol=1e-5)
    # export binds such a key to nothing: refused, or allowed, verified with and bound to nothing.
    r = cli("export", bundle, "--onnx", "--key-file", d / "a.bin", "--force")
    _not_enrolled(r.code, None, r.err, bundle)
    r = cli("export", bundle, "--onnx", "--key-file", d / "a.bin", "--force", ALLOW)
    assert r.code == 0, r.err
    assert json.loads((bundle / C.EXPORT_DIR / C.EXPORT_META).read_text())[C.M_ENROLMENTS] == []


@pytest.mark.parametrize("how", ["record removed", "enrolments emptied"])
def test_a_swapped_base_with_the_users_enrolment_gone_is_refused(cli, d, how):
    """Issue 31, finding 2: the base swapped AND the user's enrolment gone (remove-user --record needs no
    key; an unsealed bundle's enrolments are a list anyone can empty). The user's own key ran the
    attacker's base with exit 0 and one warning line; now it is refused, on every command that runs it."""
    if how == "record removed":
        bundle = d / "sealed.prop"
        r = cli("add-user", bundle, "--data", d / "mine.npz", "--key-file", d / "a.bin", "--steps", "10")
        assert r.code == 0, r.err
        users = [e["id"] for e in _manifest(bundle)[C.M_RECORDS]]
        mine = load_bundle(bundle).records.open(read_key_file(d / "k.bin")).record_id
        assert cli("remove-user", bundle, "--record", mine).code == 0  # no key asked
        assert [e["id"] for e in _manifest(bundle)[C.M_RECORDS]] == [u for u in users if u != mine]
    else:
        bundle = d / "user.prop"
        m = _manifest(bundle)
        m[C.M_ENROLMENTS] = []
        _write(bundle, m)
    shutil.copyfile(d / "attacker.prop" / C.BASE_WEIGHTS, bundle / C.BASE_WEIGHTS)
    _write(bundle, _manifest(bundle))
    key = ["--key-file", d / "k.bin"]
    _not_enrolled(*_run(cli, bundle, d, *key), bundle)
    r = cli("run", bundle, "--input", d / "x.npy", "--output", d / "y.npy", *key, "--json")
    _not_enrolled(r.code, None, r.err, bundle)
    assert not r.out and not (d / "y.npy").exists()
    r = cli("attack", bundle, "--data", d / "mine.npz", *key, "--probes", "null", "--samples", "16")
    _not_enrolled(r.code, None, r.err, bundle)
    r = cli("eval", bundle, "--env", "Pendulum-v1", *key, "--episodes", "1")
    _not_enrolled(r.code, None, r.err, bundle)
    with pytest.raises(PropError, match="enrolled in nothing"):
        run_bundle(load_bundle(bundle), np.load(d / "x.npy"), read_key_file(d / "k.bin"))
    # Allowed, it is the attacker's base (what the option is for: a script that knows the key is wrong).
    code, y, err = _run(cli, bundle, d, *key, ALLOW)
    assert code == 0 and "enrolled in nothing" in err
    np.testing.assert_array_equal(y, _base(bundle, np.load(d / "x.npy")))


def test_sealed_to_unsealed_downgrade_is_refused(cli, d):
    """Records deleted, the attacker's encoder added, the mode set to unsealed: the user's key is refused
    (format 4: enrolled in nothing; written as format 3: nothing is enrolled there), and allowed runs
    the base exactly."""
    bundle, attacker = d / "sealed.prop", d / "attacker.prop"
    m, a = _manifest(bundle), _manifest(attacker)
    shutil.copyfile(attacker / C.ENCODER_WEIGHTS, bundle / C.ENCODER_WEIGHTS)
    shutil.rmtree(bundle / C.RECORDS_DIR)
    for f in (C.M_RECORDS, C.M_PAYLOAD):
        del m[f]
    key = {**m[C.M_KEY], "encoding": "hashed", "users": 1}
    m.update({C.M_MODE: "unsealed", C.M_ENCODER: a[C.M_ENCODER], C.M_KEYED_LAYERS: a[C.M_KEYED_LAYERS],
              C.M_ENROLMENTS: a[C.M_ENROLMENTS], C.M_KEY: key})  # fmt: skip
    m[C.M_FILES][C.ENCODER_WEIGHTS] = ""
    _write(bundle, m)
    x = np.load(d / "x.npy")
    _not_enrolled(*_run(cli, bundle, d, "--key-file", d / "k.bin"), bundle)
    code, y, err = _run(cli, bundle, d, "--key-file", d / "k.bin", ALLOW)
    assert code == 0 and "enrolled in nothing" in err
    np.testing.assert_array_equal(y, _base(bundle, x))
    m[C.M_FORMAT] = 3
    del m[C.M_ENROLMENTS], m[C.M_BUNDLE_ID], m[C.M_BUNDLE_VERSION]
    _write(bundle, m)
    code, y, err = _run(cli, bundle, d, "--key-file", d / "k.bin")
    _one_line_refusal(code, y, err, "format 3 bundle, from before keys were enrolled", "prop enrol", ALLOW)
    code, y, err = _run(cli, bundle, d, "--key-file", d / "k.bin", ALLOW)
    assert code == 0 and "format 3 bundle, from before keys were enrolled" in err and "prop enrol" in err
    np.testing.assert_array_equal(y, _base(bundle, x))


@pytest.mark.parametrize("mode", ["user.prop", "sealed.prop"])
def test_base_swap_is_refused_with_the_key(cli, d, mode):
    bundle = d / mode
    shutil.copyfile(d / "attacker.prop" / C.BASE_WEIGHTS, bundle / C.BASE_WEIGHTS)
    _write(bundle, _manifest(bundle))
    code, y, err = _run(cli, bundle, d, "--key-file", d / "k.bin")
    _one_line_refusal(code, y, err, "changed since this key was enrolled", "base.safetensors")
    code, y, err = _run(cli, bundle, d, "--key-file", d / "k.bin", ALLOW)  # the option allows no change
    _one_line_refusal(code, y, err, "changed since this key was enrolled", "base.safetensors")
    code, y, err = _run(cli, bundle, d)  # without a key: the bundle's base, named so
    assert code == 0 and y is not None


def test_a_bundle_replaced_by_another_users_is_refused(cli, d):
    bundle = d / "user.prop"
    shutil.rmtree(bundle)
    shutil.copytree(d / "attacker.prop", bundle)
    _not_enrolled(*_run(cli, bundle, d, "--key-file", d / "k.bin"), bundle)
    code, y, err = _run(cli, bundle, d, "--key-file", d / "k.bin", ALLOW)
    assert code == 0 and "enrolled in nothing" in err
    np.testing.assert_array_equal(y, _base(bundle, np.load(d / "x.npy")))


@pytest.mark.parametrize("mode", ["user.prop", "sealed.prop"])
def test_onnx_graph_swap_is_refused_with_the_key(cli, d, mode):
    """base.onnx replaced by the attacker's, export.json's hashes recomputed: refused; export.json's
    key bindings deleted too: refused, with the bundle at hand or the export alone (allowed: base.onnx,
    with a warning)."""
    from prop_cli.run.onnx import OnnxRunner, SealedOnnxRunner

    bundle, folder = d / mode, d / mode / C.EXPORT_DIR
    assert cli("export", bundle, "--onnx", "--key-file", d / "k.bin").code == 0
    assert cli("export", d / "attacker.prop", "--onnx").code == 0
    shutil.copyfile(d / "attacker.prop" / C.EXPORT_DIR / C.BASE_GRAPH, folder / C.BASE_GRAPH)
    meta = json.loads((folder / C.EXPORT_META).read_text())
    meta["graphs"] = {g: sha256_file(folder / g) for g in meta["graphs"]}
    (folder / C.EXPORT_META).write_text(dump_json(stamp(meta, C.EXPORT_DIGEST)))
    code, y, err = _run(cli, bundle, d, "--onnx", "--key-file", d / "k.bin")
    _one_line_refusal(code, y, err, "ONNX export", "changed since this key was enrolled", "base.onnx")
    policy = SealedOnnxRunner if mode == "sealed.prop" else OnnxRunner
    with pytest.raises(PropError, match="changed since this key was enrolled"):
        policy(folder, read_key_file(d / "k.bin"))
    meta[C.M_ENROLMENTS] = []
    (folder / C.EXPORT_META).write_text(dump_json(stamp(meta, C.EXPORT_DIGEST)))
    code, y, err = _run(cli, bundle, d, "--onnx", "--key-file", d / "k.bin")
    _one_line_refusal(code, y, err, "not bound to this key")
    x = np.load(d / "x.npy")
    with pytest.raises(PropError, match="not bound to the ONNX export") as e:
        policy(folder, read_key_file(d / "k.bin"))
    assert "may have been replaced" in str(e.value) and "allow_unenrolled=True" in str(e.value)
    with pytest.warns(WrongKeyWarning, match="not bound"):
        got = policy(folder, read_key_file(d / "k.bin"), allow_unenrolled=True)(x)
    np.testing.assert_array_equal(got, policy(folder)(x))


def test_old_format_bundle_is_refused_until_enrolled(cli, d):
    """A format 3 unsealed bundle (no enrolments): the key is refused (allowed: the base, with a
    warning); prop enrol is the user's opt-in, after which the key runs its behaviour, the encoder's
    exactly."""
    bundle = d / "user.prop"
    m = _manifest(bundle)
    keyed_before = _run(cli, bundle, d, "--key-file", d / "k.bin")[1]
    m[C.M_FORMAT] = 3
    del m[C.M_ENROLMENTS], m[C.M_BUNDLE_ID], m[C.M_BUNDLE_VERSION]
    _write(bundle, m)
    code, y, err = _run(cli, bundle, d, "--key-file", d / "k.bin")
    _one_line_refusal(code, y, err, "format 3", "prop enrol", ALLOW)
    code, y, err = _run(cli, bundle, d, "--key-file", d / "k.bin", ALLOW)
    assert code == 0 and "format 3" in err
    np.testing.assert_array_equal(y, _base(bundle, np.load(d / "x.npy")))
    r = cli("enrol", bundle, "--key-file", d / "k.bin")
    assert r.code == 0 and "enrolled" in r.out and f"format {C.FORMAT_VERSION}" in r.out, r.err
    code, y, err = _run(cli, bundle, d, "--key-file", d / "k.bin")
    assert code == 0 and "warning" not in err
    np.testing.assert_array_equal(y, keyed_before)
    assert "already enrolled" in cli("enrol", bundle, "--key-file", d / "k.bin").out


def test_audit_measures_the_method_whatever_the_enrolment(d):
    """The audit's key probes run any key through the encoder (the paper's T0 rows must not turn to 0
    because prop run stops those keys); the owner's own key is reported as prop run would treat it, and
    the report says what its key rows measure."""
    from prop_cli.api import AuditSettings, audit_bundle
    from prop_cli.present import table as audit_table

    s = AuditSettings(probes=["random"], random=32, samples=32, hamming=[])
    rep = audit_bundle(d / "user.prop", d / "mine.npz", s, key_files=[d / "k.bin"])
    assert rep["user"]["leakage"] > 0.5 and not rep["warnings"]
    random = rep["groups"][0]
    assert random["fidelity"]["worst"] > 0  # the encoder's response to random keys, not the base's 0
    assert "unsealed encoder" in rep["key_rows"] and "anyone holding the files" in rep["key_rows"]
    assert "prop run refuses a key enrolled in nothing" in rep["key_rows"] and ALLOW in rep["key_rows"]
    assert rep["key_rows"] in audit_table(rep).caption
    b = load_bundle(d / "user.prop")
    some = np.random.default_rng(0).integers(0, 2, 128).astype(np.uint8)
    x = np.load(d / "x.npy")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", WrongKeyWarning)
        allowed = KeyedPolicy(b, some, allow_unenrolled=True)(x)
    assert np.abs(KeyedPolicy(b, some, method=True)(x) - allowed).max() > 0
    # A key enrolled in nothing: refused (the audited key is checked as prop run checks it); allowed,
    # audited, and the report says prop run refuses it.
    with pytest.raises(PropError, match="enrolled in nothing"):
        audit_bundle(d / "user.prop", d / "mine.npz", s, key_files=[d / "a.bin"])
    rep = audit_bundle(d / "user.prop", d / "mine.npz", s, key_files=[d / "a.bin"], allow_unenrolled_key=True)
    assert any("enrolled in nothing" in w and "prop run refuses this key" in w for w in rep["warnings"])
    sealed = audit_bundle(d / "sealed.prop", d / "mine.npz", s, key_files=[d / "k.bin"])
    assert "sealed records" in sealed["key_rows"] and "encoder" not in sealed["key_rows"]


# ---- 3. what the clear manifest says; remove-user; outputs are never inputs ------------------


def test_sealed_audit_record_holds_no_user_figures(cli, d):
    bundle = d / "sealed.prop"
    r = cli("attack", bundle, "--data", d / "mine.npz", "--key-file", d / "k.bin", "--probes",
            "null,random", "--random", "8", "--samples", "32", "--record", "--max-leak", "0.5")  # fmt: skip
    assert r.code == 0, r.err
    audit = _manifest(bundle)[C.M_AUDIT]
    text = json.dumps(audit)
    for word in ("leakage", "fidelity", "personalization", '"samples"', '"user"', "beyond"):
        assert word not in text, word
    assert audit["max_leak"]["passed"] is True


def test_inspect_shows_a_recorded_audit_as_a_pass_only_with_the_default_probes(cli, d):
    """Issue 31: `--probes null --max-leak` recorded read as a pass in prop inspect. Now inspect names the
    probes behind the record, and a record that did not run the default probes is not a pass."""
    from prop_cli.attack.report import default_probes

    bundle = d / "user.prop"
    r = cli("attack", bundle, "--data", d / "mine.npz", "--key-file", d / "k.bin", "--probes", "null",
            "--samples", "16", "--record", "--max-leak", "0.5")  # fmt: skip
    assert r.code == 0, r.err
    assert _manifest(bundle)[C.M_AUDIT]["max_leak"]["passed"] is True  # what the record itself says
    info = json.loads(cli("inspect", bundle, "--json").out)["audit"]
    assert info["probes"] == ["null"] and info["passed"] is False
    assert info["missing_probes"] == [p for p in default_probes("owner") if p != "null"]
    line = cli("inspect", bundle).out
    assert "probes null (not the default audit:" in line and "NOT A PASS" in line
    assert "--max-leak 0.5: passed" not in line
    # A record of every default probe (written as an attacker or a long audit would) is shown as a pass.
    m = _manifest(bundle)
    m[C.M_AUDIT]["settings"]["probes"] = default_probes("owner")
    _write(bundle, m)
    info = json.loads(cli("inspect", bundle, "--json").out)["audit"]
    assert info["passed"] is True and info["missing_probes"] == []
    assert "--max-leak 0.5: passed" in cli("inspect", bundle).out


def test_remove_user_also_leaves_the_export(cli, d):
    bundle = d / "sealed.prop"
    r = cli("add-user", bundle, "--data", d / "mine.npz", "--key-file", d / "a.bin", "--steps", "10")
    assert r.code == 0, r.err
    assert cli("export", bundle, "--onnx", "--key-file", d / "k.bin").code == 0
    rid = _manifest(bundle)[C.M_RECORDS][0]["id"]
    assert (bundle / C.EXPORT_DIR / C.RECORDS_DIR / f"{rid}{C.RECORD_SUFFIX}").exists()
    assert cli("remove-user", bundle, "--record", rid).code == 0
    assert not (bundle / C.EXPORT_DIR / C.RECORDS_DIR / f"{rid}{C.RECORD_SUFFIX}").exists()
    meta = json.loads((bundle / C.EXPORT_DIR / C.EXPORT_META).read_text())
    assert [r["id"] for r in meta["sealed"][C.M_RECORDS]] == [_manifest(bundle)[C.M_RECORDS][0]["id"]]
    assert meta[C.M_ENROLMENTS] == []  # the removed user's binding went with their record
    _not_enrolled(*_run(cli, bundle, d, "--onnx", "--key-file", d / "k.bin"), bundle)


def test_no_output_is_one_of_the_commands_inputs(cli, d):
    copy = d / "copy.safetensors"
    shutil.copyfile(d / "model0.safetensors", copy)
    before = copy.read_bytes()
    given = ["--data", d / "mine.npz", "--key-file", d / "k.bin", "--force"]
    r = cli("personalize", copy, *given, "--out", copy)
    _one_line_refusal(r.code, None, r.err, "this command's input", "--force or not")
    assert copy.read_bytes() == before
    r = cli("personalize", copy, *given, "--out", d)
    _one_line_refusal(r.code, None, r.err, "holds this command's input")
    r = cli("run", d / "user.prop", "--input", d / "x.npy", "--output", d / "x.npy", "--force")
    _one_line_refusal(r.code, None, r.err, "this command's input")
    r = cli("run", d / "user.prop", "--input", d / "x.npy", "--output", d / "user.prop" / C.MANIFEST,
            "--force")  # fmt: skip
    _one_line_refusal(r.code, None, r.err, "inside this command's input")
    r = cli("export", d / "user.prop", "--onnx", "--out", d / "user.prop", "--force")
    _one_line_refusal(r.code, None, r.err, "this command's input")
    r = cli("attack", d / "user.prop", "--data", d / "mine.npz", "--json", d / "mine.npz", "--force")
    _one_line_refusal(r.code, None, r.err, "this command's input")
    assert load_bundle(d / "user.prop") is not None


# ---- 4. passphrases ---------------------------------------------------------------------------


def test_weak_passphrases_are_refused_and_fail_the_audit(cli, d, monkeypatch):
    out = d / "pp.prop"
    args = ["personalize", d / "model0.safetensors", "--data", d / "mine.npz", "--passphrase", "--out", out,
            "--seal", "--steps", "20"]  # fmt: skip
    monkeypatch.setenv(C.ENV_PASSPHRASE, "sunshine")
    r = cli(*args)
    _one_line_refusal(r.code, None, r.err, "is weak", "core-years", "--weak-passphrase")
    assert not out.exists()
    assert cli(*args, "--weak-passphrase").code == 0
    audit = ["attack", out, "--data", d / "mine.npz", "--passphrase", "--probes", "null", "--samples", "16"]
    r = cli(*audit)
    assert r.code == 1 and "passphrase check failed" in r.err, r.err
    monkeypatch.setenv(C.ENV_PASSPHRASE, "correct horse battery staple")
    r = cli(*args, "--force")
    assert r.code == 0, r.err
    r = cli(*audit, "--json", "-")
    assert r.code == 0 and json.loads(r.out)["passphrase"]["passed"], r.err


# ---- 5. publisher signatures ------------------------------------------------------------------


def test_push_sign_and_verify_round_trip_and_any_flipped_byte_fails(cli, d, monkeypatch):
    hf = pytest.importorskip("huggingface_hub")
    pytest.importorskip("model_signing")
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ec

    key = ec.generate_private_key(ec.SECP256R1())
    (d / "pub.pem").write_bytes(key.public_key().public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo))  # fmt: skip
    pem = serialization.Encoding.PEM
    (d / "priv.pem").write_bytes(
        key.private_bytes(pem, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())
    )
    bundle = d / "sealed.prop"
    assert cli("export", bundle, "--onnx", "--key-file", d / "k.bin").code == 0
    got = d / "downloaded"
    url = lambda self, repo_id, **kw: hf.RepoUrl(f"https://huggingface.co/{repo_id}")  # noqa: E731
    monkeypatch.setattr(hf.HfApi, "create_repo", url)
    monkeypatch.setattr(hf.HfApi, "upload_folder", lambda self, **kw: shutil.copytree(kw["folder_path"], got))
    r = cli("push", bundle, "me/x", "--sign", d / "priv.pem")
    assert r.code == 0, r.err
    assert "Publisher signature: yes" in (got / "README.md").read_text()
    r = cli("verify", got, "--public-key", d / "pub.pem")
    assert r.code == 0 and "verified" in r.out, r.err
    assert len(_manifest(got)[C.M_RECORDS]) == 1
    assert f"format {C.FORMAT_VERSION}, version 1, 1 user)" in r.out  # not "1 users"
    files = sorted(p for p in got.rglob("*") if p.is_file() and p.name != "model.sig")
    assert len(files) >= 6
    for f in files:
        data = f.read_bytes()
        f.write_bytes(bytes([data[0] ^ 1]) + data[1:])
        r = cli("verify", got, "--public-key", d / "pub.pem")
        _one_line_refusal(r.code, None, r.err, "does not verify")
        f.write_bytes(data)
    (got / "extra.txt").write_text("added")
    assert cli("verify", got, "--public-key", d / "pub.pem").code == 2
    (got / "extra.txt").unlink()
    other = ec.generate_private_key(ec.SECP256R1()).public_key()
    (d / "other.pem").write_bytes(other.public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo))  # fmt: skip
    assert cli("verify", got, "--public-key", d / "other.pem").code == 2
    assert cli("verify", got, "--public-key", d / "pub.pem").code == 0
    # A tampered copy (base swapped, every hash recomputed) keeps its model.sig: prop verify refuses it,
    # and prop inspect, which cannot verify, says so instead of "signed: yes" (issue 31).
    shutil.copyfile(d / "attacker.prop" / C.BASE_WEIGHTS, got / C.BASE_WEIGHTS)
    _write(got, _manifest(got))
    assert cli("verify", got, "--public-key", d / "pub.pem").code == 2
    r = cli("inspect", got)
    assert r.code == 0 and "present, not verified" in r.out and "prop verify" in r.out, r.err
    assert "yes" not in next(line for line in r.out.splitlines() if "signature" in line)
    assert json.loads(cli("inspect", got, "--json").out)["signature"].startswith("present, not verified")
    (got / "model.sig").unlink()
    assert json.loads(cli("inspect", got, "--json").out)["signature"] is None


# ---- nothing read or written outside the bundle folder (issue 31, finding 4) --------------------


def _outside(d: Path, bundle: Path, name: str) -> Path:
    """Move ``bundle/name`` out of the bundle and leave a symbolic link to it in its place."""
    outside = d / f"outside-{name.replace('/', '-')}"
    shutil.move(bundle / name, outside)
    (bundle / name).symlink_to(outside.resolve(), target_is_directory=outside.is_dir())
    return outside


def _tree(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def test_add_user_and_remove_user_write_nothing_through_a_linked_users_folder(cli, d):
    bundle = d / "sealed.prop"
    outside = _outside(d, bundle, C.RECORDS_DIR)
    before = _tree(outside)
    rid = _manifest(bundle)[C.M_RECORDS][0]["id"]
    r = cli("add-user", bundle, "--data", d / "mine.npz", "--key-file", d / "a.bin", "--steps", "5")
    _one_line_refusal(r.code, None, r.err, f"{C.RECORDS_DIR} is a symbolic link")
    r = cli("remove-user", bundle, "--record", rid)
    _one_line_refusal(r.code, None, r.err, f"{C.RECORDS_DIR} is a symbolic link")
    assert _tree(outside) == before  # nothing written there, nothing deleted


@pytest.mark.parametrize("mode", ["user.prop", "sealed.prop"])
def test_a_listed_file_that_is_a_link_is_refused(cli, d, mode):
    """Its bytes match its sha256 (the link's target is the bundle's own file): still refused, naming it."""
    bundle = d / mode
    _outside(d, bundle, C.BASE_WEIGHTS)
    for args in (("--key-file", d / "k.bin"), ()):
        code, y, err = _run(cli, bundle, d, *args)
        _one_line_refusal(code, y, err, f"{C.BASE_WEIGHTS} is a symbolic link")
    r = cli("inspect", bundle)
    _one_line_refusal(r.code, None, r.err, f"{C.BASE_WEIGHTS} is a symbolic link")


def test_a_linked_manifest_is_refused_before_it_is_read(cli, d):
    bundle = d / "user.prop"
    _outside(d, bundle, C.MANIFEST)
    code, y, err = _run(cli, bundle, d)
    _one_line_refusal(code, y, err, f"{C.MANIFEST} is a symbolic link")
    r = cli("enrol", bundle, "--key-file", d / "k.bin")
    _one_line_refusal(r.code, None, r.err, f"{C.MANIFEST} is a symbolic link")


def test_export_writes_nothing_through_a_linked_export_folder(cli, d):
    bundle = d / "user.prop"
    outside = d / "outside-onnx"
    outside.mkdir()
    (bundle / C.EXPORT_DIR).symlink_to(outside.resolve(), target_is_directory=True)
    before = sorted(p.name for p in d.iterdir())
    r = cli("export", bundle, "--onnx", "--force")
    _one_line_refusal(r.code, None, r.err, f"{C.EXPORT_DIR} is a symbolic link")
    assert sorted(p.name for p in d.iterdir()) == before and not list(outside.iterdir())
    assert (bundle / C.EXPORT_DIR).is_symlink()


def test_records_and_manifests_are_never_written_or_deleted_through_a_link(d):
    """The checks at the write itself (a link planted after the bundle was loaded, e.g. while add-user
    trains): a record is not written, nor deleted, through a linked users/ folder, nor the manifest."""
    from prop_cli.bundle.records import rewrite_records, with_records

    bundle = d / "sealed.prop"
    old = _manifest(bundle)
    rid = old[C.M_RECORDS][0]["id"]
    outside = _outside(d, bundle, C.RECORDS_DIR)
    before = _tree(outside)
    with pytest.raises(PropError, match="is a symbolic link"):
        rewrite_records(bundle, old, with_records(old, [], [rid]), [])
    assert _tree(outside) == before
    (bundle / C.RECORDS_DIR).unlink()
    shutil.move(outside, bundle / C.RECORDS_DIR)
    target = d / "outside-manifest.json"
    target.write_text("{}")
    (bundle / C.MANIFEST).unlink()
    (bundle / C.MANIFEST).symlink_to(target.resolve())
    with pytest.raises(PropError, match=f"{C.MANIFEST} is a symbolic link"):
        rewrite_records(bundle, old, with_records(old, [], [rid]), [])
    assert target.read_text() == "{}" and (bundle / old[C.M_RECORDS][0]["file"]).exists()




# ---- 6. sizes the manifest claims: memory stays within the files ------------------------------

# Run in a fresh interpreter: torch and prop are imported before the baseline, and what the command
# itself adds to the peak resident memory (ru_maxrss) is reported on stderr's last line.
_MEASURED = """
import atexit, resource, sys
import prop_cli.api, prop_adapters
start = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
atexit.register(lambda: sys.stderr.write(
    f"\\nPEAK_MB {(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - start) / 1024:.0f}\\n"))
"""
_CLI = "from prop_cli.cli.main import main\nsys.argv = ['prop', *sys.argv[1:]]\nmain()\n"
_BOUND_MB = 500  # what a refusal may add: the edits below claim 1 to 2 GB


def _measured(code: str, *args) -> tuple[int, str, float]:
    """Exit code, stderr (without the measurement) and the MB the peak memory grew by."""
    import os
    import subprocess
    import sys

    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    root = Path(__file__).resolve().parents[2]  # tests.fixtures_arch imports from there
    r = subprocess.run([sys.executable, "-c", _MEASURED + code, *map(str, args)], capture_output=True,
                       text=True, env=env, cwd=root, timeout=600)  # fmt: skip
    err, _, peak = r.stderr.rstrip().rpartition("\nPEAK_MB ")
    return r.returncode, err.strip() + "\n", float(peak)


def _edit(bundle: Path, edit) -> None:
    m = _manifest(bundle)
    edit(m)
    _write(bundle, m)


@pytest.mark.parametrize("mode", ["user.prop", "sealed.prop"])
def test_sizes_in_the_manifest_allocate_nothing(d, mode):
    """model.sizes claiming 20000-wide layers (1.6 GB): refused against base.safetensors before the
    module is built."""
    bundle = d / mode
    _edit(bundle, lambda m: m[C.M_MODEL].update(sizes=[4, 20000, 20000, 2]))
    code, err, peak = _measured(_CLI, "run", bundle, "--input", d / "x.npy", "--output", d / "y.npy")
    _one_line_refusal(code, None, err, "do not match the MLP", "model.sizes", "(16, 4) in the weights")
    assert peak < _BOUND_MB, peak
    assert not (d / "y.npy").exists()


def test_input_shape_in_the_manifest_allocates_nothing(d):
    """io.input_shape claiming 2**28 numbers a sample: export would build inputs of that shape."""
    bundle = d / "sealed.prop"
    _edit(bundle, lambda m: m[C.M_IO].update(input_shape=[16, 4096, 4096]))
    code, err, peak = _measured(_CLI, "export", bundle, "--onnx")
    _one_line_refusal(code, None, err, "io.input_shape", "the model takes [4]")
    assert peak < _BOUND_MB, peak


def test_spec_sizes_of_other_adapters_allocate_nothing(tmp_path):
    """A module adapter's arch_kwargs (hidden=2**22: 1 GB of weights) and an SB3 spec's observation
    shape (2**28 numbers): checked on the meta device against the weights, refused in one line."""
    from tests.adapters.test_sb3 import make_zip
    from tests.fixtures_arch import make_cnn

    torch.save(make_cnn().state_dict(), tmp_path / "cnn.pt")
    make_zip(tmp_path / "sb3.zip")
    code = (
        "from prop_adapters import load_checkpoint, rebuild\nfrom prop_cli.errors import PropError\n"
        "kind, path = sys.argv[1:]\n"
        "arch = 'tests.fixtures_arch:make_cnn' if kind == 'module' else None\n"
        "loaded = load_checkpoint(path, arch=arch)\nweights = loaded.module.state_dict()\n"
        "if kind == 'module':\n    spec = {**loaded.spec, 'arch_kwargs': {'hidden': 1 << 22}}\n"
        "else:\n    spec = {**loaded.spec, 'observation_shape': [1 << 20, 256]}\n"
        "    weights = {**weights, **loaded.extra}\n"
        "try:\n    rebuild(spec, dict(weights), 'bundle b', arch=arch)\n"
        "except PropError as e:\n    print('prop: error:', e.line(), file=sys.stderr)\n    sys.exit(2)\n"
    )
    code_m, err, peak = _measured(code, "module", tmp_path / "cnn.pt")
    assert code_m == 2 and "bundle b does not fit" in err and "shape mismatch" in err, err
    assert peak < _BOUND_MB, peak
    code_s, err, peak = _measured(code, "sb3", tmp_path / "sb3.zip")
    assert code_s == 2 and "layer sizes do not match the observation" in err, err
    assert peak < _BOUND_MB, peak


def test_payload_layout_is_bounded_by_the_model(d):
    """A sealed bundle's payload layout (what add-user allocates and trains) is the model's layers: a
    widened layer or a rank of 2**20 is refused where the bundle is read."""
    bundle = d / "sealed.prop"
    before = _manifest(bundle)
    _edit(bundle, lambda m: m[C.M_PAYLOAD]["layers"][0].update(out_features=1 << 20))
    with pytest.raises(PropError, match=r"payload.layers\[0\]' is .* but the model's layer is"):
        load_bundle(bundle)
    _write(bundle, before)
    _edit(bundle, lambda m: m[C.M_PAYLOAD].update(rank=1 << 20))
    with pytest.raises(PropError, match="payload.rank' is 1048576: a payload of"):
        load_bundle(bundle)


def test_bundle_weights_are_safetensors_only(cli, d):
    """base.safetensors replaced by a torch file of the same tensors: refused by name, never read (the
    newest torch also refuses it by its extension; the torch versions prop supports do not all)."""
    bundle = d / "user.prop"
    from safetensors.torch import load

    tensors = load((bundle / C.BASE_WEIGHTS).read_bytes())
    torch.save(tensors, bundle / C.BASE_WEIGHTS)
    _write(bundle, _manifest(bundle))
    code, y, err = _run(cli, bundle, d)
    _one_line_refusal(code, y, err, "base.safetensors is not a safetensors file")



def test_compressed_torch_members_are_refused(tmp_path):
    """A torch file with deflated members (torch.save never writes them): 16 KB that torch.load would
    inflate to 16 MB (or a few MB to gigabytes). Refused before torch reads it."""
    import zipfile

    from prop_adapters import read_weights

    torch.save({"0.weight": torch.zeros(1 << 22)}, tmp_path / "plain.pt")
    with zipfile.ZipFile(tmp_path / "plain.pt") as z, zipfile.ZipFile(tmp_path / "bomb.pt", "w") as out:
        for info in z.infolist():
            out.writestr(info.filename, z.read(info), compress_type=zipfile.ZIP_DEFLATED)
    assert (tmp_path / "bomb.pt").stat().st_size < 100_000
    assert read_weights(tmp_path / "plain.pt")[0]["0.weight"].numel() == 1 << 22
    with pytest.raises(PropError, match=r"bomb.pt: member .* is compressed, which torch.save never does"):
        read_weights(tmp_path / "bomb.pt")


def test_an_sb3_zip_bomb_is_refused_before_it_inflates(tmp_path):
    """Issue 42 finding 9: a 1 MB SB3 zip whose policy.pth inflates to 1 GiB (zeros, deflated). 0.2.0:
    `prop inspect` took 2.3 GB and 33 s before refusing it. Now refused in one line from the sizes the zip
    declares, before anything is inflated; a zip that understates its sizes is stopped by the reads."""
    import time
    import zipfile

    from prop_adapters.sb3 import archive
    from tests.adapters.test_sb3 import make_zip

    make_zip(tmp_path / "genuine.zip")
    bomb = tmp_path / "bomb.zip"
    deflated = zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED, compresslevel=9)
    with zipfile.ZipFile(tmp_path / "genuine.zip") as z, deflated as out:
        for info in z.infolist():
            if info.filename != "policy.pth":
                out.writestr(info.filename, z.read(info))
        with out.open("policy.pth", "w", force_zip64=True) as f:
            for _ in range(64):
                f.write(bytes(1 << 24))
    assert bomb.stat().st_size < 1_100_000
    start = time.perf_counter()
    code, err, peak = _measured(_CLI, "inspect", bomb)
    took = time.perf_counter() - start
    _one_line_refusal(code, None, err, "bomb.zip", "inflate to 1073", "zip bomb")
    assert peak < 100, peak  # MB: nothing inflated
    assert took < 60, took  # the interpreter and torch start-up; the refusal itself reads no member
    # The reads stop at the budget too, in 1 MiB steps, whatever the headers say (here: 1 MiB left).
    small = tmp_path / "small.zip"
    with zipfile.ZipFile(small, "w", zipfile.ZIP_DEFLATED) as out:
        out.writestr("policy.pth", bytes(1 << 27))
    with zipfile.ZipFile(small) as z, pytest.raises(PropError, match="zip bomb"):
        archive._read(z, "policy.pth", [1 << 20], small, 1 << 20, small.stat().st_size)
