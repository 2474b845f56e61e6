"""Rollback and replay (issue 31, finding 3), built as an attacker would: an older copy of a bundle put
back, an older record or enrolment put back after its user re-enrolled, an older signed revision. Each is
refused in one line on a machine that has seen newer; --allow-rollback accepts it with a warning; a
machine that has seen nothing (a fresh state folder) accepts it: the documented limit."""

from __future__ import annotations

import hashlib
import json
import shutil
import threading
from pathlib import Path

import numpy as np
import pytest
from safetensors.torch import load_file, save_file

from prop_cli import constants as C
from prop_cli.bundle import rollback
from prop_cli.bundle.manifest import stamp
from prop_cli.files import dump_json, sha256_file
from tests.conftest import FAST

VERSION = C.M_BUNDLE_VERSION


def _manifest(bundle: Path) -> dict:
    return json.loads((bundle / C.MANIFEST).read_text())


def _write(bundle: Path, m: dict) -> None:
    """What an attacker does after an edit: every listed file's sha256 and the manifest digest again."""
    m[C.M_FILES] = {name: sha256_file(bundle / name) for name in m[C.M_FILES]}
    (bundle / C.MANIFEST).write_text(dump_json(stamp(m)))


def _restore(copy: Path, bundle: Path) -> None:
    """The attacker puts an older copy of the folder back in place."""
    shutil.rmtree(bundle)
    shutil.copytree(copy, bundle)


def _run(cli, bundle: Path, d: Path, key: str, *extra: str):
    out = d / "y.npy"
    out.unlink(missing_ok=True)
    r = cli("run", bundle, "--input", d / "x.npy", "--output", out, "--key-file", d / key, "--json", *extra)
    keyed = json.loads(r.out)["keyed"] if r.code == 0 else None
    return r, keyed


def _refused(r, *words: str) -> None:
    assert r.code == 2, r.err
    assert r.err.count("\n") == 1 and r.err.startswith("prop: error:"), r.err
    for w in ("--allow-rollback", *words):
        assert w in r.err, r.err


def _sealed(cli, d: Path) -> Path:
    """A sealed bundle of one user (k.bin)."""
    b = d / "sealed.prop"
    r = cli("personalize", d / "model.safetensors", "--data", d / "mine.npz", "--key-file", d / "k.bin",
            "--out", b, *FAST, "--seal")  # fmt: skip
    assert r.code == 0, r.err
    return b


def _sealed_with_second_user(cli, d: Path) -> Path:
    b = _sealed(cli, d)
    r = cli("add-user", b, "--data", d / "mine.npz", "--key-file", d / "k2.bin", "--steps", "20")
    assert r.code == 0, r.err
    return b


def _runs_with_the_option_or_on_a_new_machine(cli, b, workdir, key, monkeypatch, tmp_path_factory) -> None:
    """What the refusal leaves open: --allow-rollback runs the copy keyed, and so does a machine that has
    seen nothing of the bundle (the documented limit)."""
    r, keyed = _run(cli, b, workdir, key, "--allow-rollback")
    assert r.code == 0 and keyed, r.err
    monkeypatch.setenv(C.ENV_STATE_DIR, str(tmp_path_factory.mktemp("new-machine")))
    assert _run(cli, b, workdir, key)[1] is True


def _personalize(cli, workdir: Path, out: Path, *extra) -> None:
    """An unsealed bundle of the user's key (k.bin) at ``out``."""
    r = cli("personalize", workdir / "model.safetensors", "--data", workdir / "mine.npz",
            "--key-file", workdir / "k.bin", "--out", out, *FAST, *extra)  # fmt: skip
    assert r.code == 0, r.err


def test_every_write_increases_the_version_and_keeps_the_id(cli, workdir):
    b = _sealed_with_second_user(cli, workdir)
    m = _manifest(b)
    assert m[C.M_FORMAT] == C.FORMAT_VERSION == 6 and m[VERSION] == 2 and len(m[C.M_BUNDLE_ID]) == 32
    r = cli("remove-user", b, "--record", m[C.M_RECORDS][1]["id"])
    assert r.code == 0, r.err
    assert _manifest(b)[VERSION] == 3 and _manifest(b)[C.M_BUNDLE_ID] == m[C.M_BUNDLE_ID]
    u = workdir / "u.prop"
    r = cli("personalize", workdir / "model.safetensors", "--data", workdir / "mine.npz",
            "--key-file", workdir / "k.bin", "--out", u, *FAST)  # fmt: skip
    assert r.code == 0 and _manifest(u)[VERSION] == 1, r.err
    assert _manifest(u)[C.M_BUNDLE_ID] != m[C.M_BUNDLE_ID]  # random per bundle
    assert cli("enrol", u, "--key-file", workdir / "k2.bin").code == 0
    assert _manifest(u)[VERSION] == 2
    assert cli("enrol", u, "--key-file", workdir / "k2.bin").code == 0  # already enrolled: nothing written
    assert _manifest(u)[VERSION] == 2
    from prop_cli.bundle import update_manifest  # what prop attack --record writes with

    update_manifest(u, C.M_AUDIT, {"schema": "test"})
    assert _manifest(u)[VERSION] == 3 and _manifest(u)[C.M_AUDIT] == {"schema": "test"}


def test_an_older_copy_gives_a_removed_user_nothing(cli, workdir, monkeypatch, tmp_path_factory):
    """Copy the folder before remove-user, put the copy back: the removed user's key is refused."""
    b = _sealed_with_second_user(cli, workdir)
    r, keyed = _run(cli, b, workdir, "k2.bin")
    assert r.code == 0 and keyed, r.err
    old = workdir / "copy.prop"
    shutil.copytree(b, old)
    assert cli("remove-user", b, "--key-file", workdir / "k2.bin").code == 0
    _restore(old, b)
    r, _ = _run(cli, b, workdir, "k2.bin")
    _refused(r, "older copy", "removed from it at version 3")
    assert not (workdir / "y.npy").exists()
    # Its version edited past the one seen here, digest recomputed: the record was still removed here.
    m = _manifest(b)
    m[VERSION] = 99
    _write(b, m)
    _refused(_run(cli, b, workdir, "k2.bin")[0], "removed")
    # The remaining user's key: this copy's manifest is newer than any seen, their record not removed.
    assert _run(cli, b, workdir, "k.bin")[1] is True
    r, keyed = _run(cli, b, workdir, "k2.bin", "--allow-rollback")
    assert r.code == 0 and keyed and "prop: warning:" in r.err and "--allow-rollback" in r.err, r.err
    # A machine that never saw the newer version (a fresh state folder) cannot tell: the limit.
    monkeypatch.setenv(C.ENV_STATE_DIR, str(tmp_path_factory.mktemp("new-machine")))
    r, keyed = _run(cli, b, workdir, "k2.bin")
    assert r.code == 0 and keyed and "warning" not in r.err, r.err


def test_an_older_record_put_back_after_add_user_again_is_refused(
    cli, workdir, monkeypatch, tmp_path_factory
):
    """The user re-enrols (remove-user, add-user again); the attacker puts their older record back into
    the current manifest in place of the new one, or the whole older folder back: refused."""
    b = _sealed_with_second_user(cli, workdir)
    old = workdir / "copy.prop"
    shutil.copytree(b, old)
    first = _manifest(b)[C.M_RECORDS][1]
    assert cli("remove-user", b, "--key-file", workdir / "k2.bin").code == 0
    r = cli("add-user", b, "--data", workdir / "mine.npz", "--key-file", workdir / "k2.bin", "--steps", "20")
    assert r.code == 0 and _manifest(b)[VERSION] == 4, r.err
    assert _run(cli, b, workdir, "k2.bin")[1] is True
    m = _manifest(b)
    now = m[C.M_RECORDS][1]
    shutil.copyfile(old / first["file"], b / first["file"])
    (b / now["file"]).unlink()
    m[C.M_RECORDS][1] = first
    _write(b, m)
    assert len(_manifest(b)[C.M_RECORDS]) == 2
    _refused(_run(cli, b, workdir, "k2.bin")[0], "older copy")
    _restore(old, b)
    _refused(_run(cli, b, workdir, "k2.bin")[0], "older copy")
    _runs_with_the_option_or_on_a_new_machine(cli, b, workdir, "k2.bin", monkeypatch, tmp_path_factory)


def _owner_update(bundle: Path) -> None:
    """The owner changes an unsealed bundle (a new encoder), as a retraining would."""
    f = bundle / C.ENCODER_WEIGHTS
    enc = load_file(f)
    save_file({k: v * 1.01 for k, v in enc.items()}, str(f))
    m = _manifest(bundle)
    _write(bundle, m)


def test_an_older_enrolment_put_back_after_enrol_again_is_refused(
    cli, workdir, monkeypatch, tmp_path_factory
):
    """Unsealed: the owner updates the bundle and the user enrols again (prop enrol); the older copy,
    with the user's older enrolment and the older behaviour it matches, is refused with their key."""
    b = workdir / "u.prop"
    _personalize(cli, workdir, b)
    old = workdir / "copy.prop"
    shutil.copytree(b, old)
    _owner_update(b)
    assert _run(cli, b, workdir, "k.bin")[0].code == 2  # changed since enrolled: the user must accept it
    r = cli("enrol", b, "--key-file", workdir / "k.bin")
    assert r.code == 0 and "re-enrolled" in r.out and _manifest(b)[VERSION] == 2, r.out + r.err
    _restore(old, b)
    _refused(_run(cli, b, workdir, "k.bin")[0], "older copy", "version 1")
    m = _manifest(b)
    m[VERSION] = 7  # past the version seen here: the enrolment inside is still version 1
    _write(b, m)
    _refused(_run(cli, b, workdir, "k.bin")[0], "its enrolment of version 2")
    _runs_with_the_option_or_on_a_new_machine(cli, b, workdir, "k.bin", monkeypatch, tmp_path_factory)


def test_a_downgraded_or_moved_enrolment_is_changed(cli, workdir):
    """Rollback protection cannot be stripped by writing the manifest as format 4, nor a record moved
    from a copy of the bundle under another id: the bundle id is part of what each key enrolled in."""
    b = workdir / "u.prop"
    _personalize(cli, workdir, b)
    m = _manifest(b)
    m[C.M_FORMAT] = 4
    del m[C.M_BUNDLE_ID], m[VERSION]
    _write(b, m)
    r, _ = _run(cli, b, workdir, "k.bin")
    assert r.code == 2 and "changed since this key was enrolled (bundle id differ)" in r.err, r.err
    m = _manifest(b)
    m.update({C.M_FORMAT: 5, C.M_BUNDLE_ID: "ab" * 16, VERSION: 1})
    _write(b, m)
    r, _ = _run(cli, b, workdir, "k.bin")
    assert r.code == 2 and "(bundle id differ)" in r.err, r.err


def _signing_keys(d: Path) -> None:
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ec

    key = ec.generate_private_key(ec.SECP256R1())
    pem = serialization.Encoding.PEM
    public = serialization.PublicFormat.SubjectPublicKeyInfo
    (d / "pub.pem").write_bytes(key.public_key().public_bytes(pem, public))
    (d / "priv.pem").write_bytes(
        key.private_bytes(pem, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())
    )


def test_an_older_signed_revision_is_refused_by_verify(cli, workdir, monkeypatch, tmp_path_factory):
    pytest.importorskip("model_signing")
    from prop_cli.deploy.sign import sign_folder

    _signing_keys(workdir)
    b = workdir / "u.prop"
    _personalize(cli, workdir, b)
    revs = []
    for i in (1, 2):
        if i == 2:
            assert cli("enrol", b, "--key-file", workdir / "k2.bin").code == 0  # the publisher's next write
        rev = workdir / f"rev{i}"
        shutil.copytree(b, rev)
        sign_folder(rev, workdir / "priv.pem")
        revs.append(rev)

    def verify(rev: Path, *extra: str):
        return cli("verify", rev, "--public-key", workdir / "pub.pem", *extra)

    r = verify(revs[1])
    assert r.code == 0 and "version 2" in r.out, r.err
    r = verify(revs[0])
    assert r.code == 2 and r.err.count("\n") == 1 and "older signed revision" in r.err, r.err
    assert "version 1" in r.err and "--allow-rollback" in r.err
    r = verify(revs[0], "--allow-rollback")
    assert r.code == 0 and "prop: warning:" in r.err, r.err
    assert verify(revs[1]).code == 0  # the newest stays accepted
    # The verified version is the publisher's: a key is refused the older copy too.
    _refused(_run(cli, revs[0], workdir, "k.bin")[0], "older copy")
    monkeypatch.setenv(C.ENV_STATE_DIR, str(tmp_path_factory.mktemp("new-machine")))
    assert verify(revs[0]).code == 0  # nothing verified here before: the limit


def test_the_state_holds_no_key_material_and_survives_concurrent_writers(cli, workdir, _own_state_dir):
    b = _sealed_with_second_user(cli, workdir)
    assert _run(cli, b, workdir, "k2.bin")[1] is True
    files = [f for f in _own_state_dir.rglob("*") if f.is_file()]
    assert [f.name for f in files if f.suffix == ".json"] == [f"{_manifest(b)[C.M_BUNDLE_ID]}.json"]
    for name in ("k.bin", "k2.bin"):
        key = (workdir / name).read_bytes()
        digest = hashlib.sha256(key)
        secrets = [key, key.hex().encode(), digest.hexdigest().encode(), digest.digest()]
        assert not any(s in f.read_bytes() for f in files for s in secrets)
    # Writers in parallel (their own file handles, as separate processes would have): none is lost.
    m = _manifest(b)
    ids = [f"{i:016x}" for i in range(12)]
    threads = [threading.Thread(target=rollback.wrote, args=(m,), kwargs={"users": {i: 5}}) for i in ids]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    state = json.loads((_own_state_dir / "bundles" / f"{m[C.M_BUNDLE_ID]}.json").read_text())
    secret = (_own_state_dir / C.STATE_SECRET).read_bytes()  # the ids are kept HMAC'd under it
    hids = {rollback._hid(secret, m[C.M_BUNDLE_ID], i) for i in ids}
    assert hids <= set(state["users"]) and state["version"] == m[VERSION]
    assert not any(i in json.dumps(state) for i in ids)


def test_a_format_4_bundle_is_version_0_and_the_new_fields_have_rules(cli, workdir, _own_state_dir):
    """Bundles written before versions (format 4, tests/fixtures/bundles-0.1) run with their key as before
    and nothing is remembered of them; format 4 cannot carry the new fields, format 5 must."""
    from prop_cli.api import load_bundle, read_key_file, run_bundle
    from tests.fixtures import v01

    fx = v01.load("mlp-sealed-lora")
    run = next(r for r in fx.runs if r["name"] == "user" and not r["onnx"])
    y = run_bundle(load_bundle(fx.bundle), np.load(fx.input), read_key_file(fx.key(run["key_file"], workdir)))
    assert v01.same(y, fx.expected(run))
    assert not any(_own_state_dir.rglob("*.json"))
    r = cli("inspect", fx.bundle, "--json")
    assert r.code == 0 and json.loads(r.out)["bundle_version"] == 0, r.err
    # prop enrol makes a format 4 bundle the current format; the enrolments already there stay valid.
    fx = v01.load("mlp-unsealed")
    copy = workdir / "v01.prop"
    shutil.copytree(fx.bundle, copy)
    r = cli("enrol", copy, "--key-file", fx.key("wrong.bin", workdir))
    assert r.code == 0 and f"format {C.FORMAT_VERSION}" in r.out, r.err
    assert _manifest(copy)[VERSION] == 1 and len(_manifest(copy)[C.M_ENROLMENTS]) == 2
    user = next(r for r in fx.runs if r["name"] == "user" and not r["onnx"])
    out = workdir / "y.npy"
    r = cli("run", copy, "--input", fx.input, "--output", out, "--key-file", fx.key("k.bin", workdir))
    assert r.code == 0 and "(keyed)" in r.err and v01.same(np.load(out), fx.expected(user)), r.err
    b = workdir / "u.prop"
    _personalize(cli, workdir, b)
    m = _manifest(b)
    m[C.M_FORMAT] = 4
    _write(b, m)
    r = cli("inspect", b)
    assert r.code == 2 and "'bundle_id' is not a field of format 4 bundles" in r.err, r.err
    del m[C.M_BUNDLE_ID]
    m[C.M_FORMAT] = 5
    _write(b, m)
    r = cli("inspect", b)
    assert r.code == 2 and "'bundle_id' is missing" in r.err, r.err
