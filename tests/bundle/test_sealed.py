"""Sealed bundles: base = the original, each user's payload encrypted; users added and removed alone."""

from __future__ import annotations

import hashlib
import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from prop_cli import constants as C
from prop_cli.api import load_bundle, read_key_file
from prop_cli.bundle.cipher import SealedRecord, open_record, seal
from prop_cli.bundle.manifest import stamp
from prop_cli.files import dump_json
from prop_cli.run.policy import KeyedPolicy, WrongKeyWarning
from tests.conftest import FAST

SEALED = [*FAST[:1], "300", *FAST[2:], "--seal"]  # enough steps for the payload to fit the tiny task


@pytest.fixture
def sealed(cli, workdir) -> Path:
    out = workdir / "sealed.prop"
    r = cli("personalize", workdir / "model.safetensors", "--data", workdir / "mine.npz",
            "--key-file", workdir / "k.bin", "--out", out, *SEALED)  # fmt: skip
    assert r.code == 0, r.err
    return out


def _run(cli, bundle: Path, workdir: Path, *key: str) -> tuple[np.ndarray, str]:
    out = workdir / "y.npy"
    r = cli("run", bundle, "--input", workdir / "x.npy", "--output", out, "--force", *key)
    assert r.code == 0, r.err
    return np.load(out), r.err


def _original(workdir: Path) -> np.ndarray:
    b = load_bundle(workdir / "sealed.prop")  # its base is the checkpoint, byte for byte
    with torch.no_grad():
        return b.loaded.module(torch.from_numpy(np.load(workdir / "x.npy"))).numpy()


def test_seal_roundtrip_and_tamper():
    ad = lambda rid: b"bundle:" + rid.encode()  # noqa: E731
    bits = np.random.default_rng(0).integers(0, 2, 128).astype(np.uint8)
    rec = seal(b"payload", bits, ad)
    assert open_record(rec, bits, ad(rec.id)) == b"payload"
    other = bits.copy()
    other[5] ^= 1
    assert open_record(rec, other, ad(rec.id)) is None  # one bit off: nothing
    assert open_record(rec, bits, b"bundle:edited") is None  # other associated data: nothing
    flipped = bytearray(rec.ciphertext)
    flipped[0] ^= 1
    assert open_record(SealedRecord(rec.id, rec.salt, rec.nonce, bytes(flipped)), bits, ad(rec.id)) is None


def test_sealed_bundle_holds_the_original_and_no_key(sealed, workdir):
    assert (sealed / C.BASE_WEIGHTS).read_bytes() == (workdir / "model.safetensors").read_bytes()
    assert not (sealed / C.ENCODER_WEIGHTS).exists()
    m = json.loads((sealed / C.MANIFEST).read_text())
    assert m[C.M_MODE] == C.MODE_SEALED and len(m[C.M_RECORDS]) == 1
    # The clear manifest holds no figure, count or path of a user: their report is sealed with them.
    public = {k: v for k, v in m.items() if k != C.M_CONFIG}  # config: the shared training settings
    assert C.M_METRICS not in m and "samples" not in json.dumps(public) and "source" not in m[C.M_KEY]
    assert m[C.M_IO]["checkpoint"] == "model.safetensors"
    sizes = {(sealed / r["file"]).stat().st_size % 4096 for r in m[C.M_RECORDS]}
    assert sizes == {16}  # padded to 4 KiB buckets (+ the GCM tag)
    key = (workdir / "k.bin").read_bytes()
    secrets = [
        key,
        key.hex().encode(),
        hashlib.sha256(key).hexdigest().encode(),
        hashlib.sha256(key).digest(),
    ]
    for f in sealed.rglob("*"):
        if f.is_file():
            data = f.read_bytes()
            assert not any(s in data for s in secrets), f


def test_user_key_personalizes_and_wrong_keys_run_the_original(cli, sealed, workdir):
    y_user, _ = _run(cli, sealed, workdir, "--key-file", workdir / "k.bin")
    y_none, _ = _run(cli, sealed, workdir)
    y_wrong, err = _run(cli, sealed, workdir, "--key-file", workdir / "k2.bin", "--allow-unenrolled-key")
    x = np.load(workdir / "x.npy")
    target = -x[:, :2] * 0.5
    base_err = ((y_none - target) ** 2).mean()
    assert ((y_user - target) ** 2).mean() < 0.2 * base_err
    np.testing.assert_array_equal(y_none, _original(workdir))
    np.testing.assert_array_equal(y_wrong, y_none)  # exactly the original
    assert "enrolled in nothing" in err and "the bundle's base" in err
    # Every 1-bit neighbour of the user's key: exactly the original too.
    bundle = load_bundle(sealed)
    bits = read_key_file(workdir / "k.bin")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", WrongKeyWarning)
        for i in range(0, 128, 9):
            near = bits.copy()
            near[i] ^= 1
            np.testing.assert_array_equal(KeyedPolicy(bundle, near, allow_unenrolled=True)(x), y_none)


def test_edited_manifest_is_refused_with_the_key(cli, sealed, workdir):
    m = json.loads((sealed / C.MANIFEST).read_text())
    m[C.M_TASK] = "classification"  # shapes what the payload's outputs mean
    (sealed / C.MANIFEST).write_text(json.dumps(m))
    r = cli("run", sealed, "--input", workdir / "x.npy", "--output", workdir / "z.npy")
    assert r.code == 2 and "does not match its manifest_sha256" in r.err  # the digest sees the edit
    # An editor who recomputes the digest gets past it; the record's enrolment does not.
    (sealed / C.MANIFEST).write_text(dump_json(stamp(m)))
    r = cli("run", sealed, "--input", workdir / "x.npy", "--output", workdir / "z.npy",
            "--key-file", workdir / "k.bin")  # fmt: skip
    assert r.code == 2 and "changed since this key was enrolled (task differ)" in r.err
    assert r.err.count("\n") == 1 and not (workdir / "z.npy").exists()
    rec = sealed / m[C.M_RECORDS][0]["file"]
    rec.write_bytes(rec.read_bytes()[:-1] + b"\0")
    # Format 6: a record is read and checked when a key tries it (inspect and verify check every one).
    r = cli("run", sealed, "--input", workdir / "x.npy", "--output", workdir / "z.npy",
            "--key-file", workdir / "k.bin")  # fmt: skip
    assert r.code == 2 and "sha256" in r.err and not (workdir / "z.npy").exists()
    r = cli("inspect", sealed)
    assert r.code == 2 and "sha256" in r.err


def test_add_and_remove_users_independently(cli, sealed, workdir):
    rng = np.random.default_rng(1)
    x = rng.uniform(-1, 1, (200, 4)).astype(np.float32)
    np.savez(workdir / "theirs.npz", x=x, y=(x[:, 2:] * 0.7).astype(np.float32))
    first = {f.name: f.read_bytes() for f in (sealed / C.RECORDS_DIR).iterdir()}
    r = cli("add-user", sealed, "--data", workdir / "theirs.npz", "--key-file", workdir / "k2.bin",
            "--steps", "300", "--device", "cpu", "--json")  # fmt: skip
    assert r.code == 0, r.err
    added = json.loads(r.out)
    assert added["users"] == 2 and added["metrics"]["personalization"] > 0.5
    for name, data in first.items():  # the first user's record is untouched
        assert (sealed / C.RECORDS_DIR / name).read_bytes() == data
    xs = np.load(workdir / "x.npy")
    y1, _ = _run(cli, sealed, workdir, "--key-file", workdir / "k.bin")
    y2, _ = _run(cli, sealed, workdir, "--key-file", workdir / "k2.bin")
    assert ((y1 + xs[:, :2] * 0.5) ** 2).mean() < ((y2 + xs[:, :2] * 0.5) ** 2).mean()
    assert ((y2 - xs[:, 2:] * 0.7) ** 2).mean() < ((y1 - xs[:, 2:] * 0.7) ** 2).mean()

    again = cli("add-user", sealed, "--data", workdir / "theirs.npz", "--key-file", workdir / "k2.bin")
    assert again.code == 2 and "already opens" in again.err
    r = cli("remove-user", sealed, "--key-file", workdir / "k2.bin")
    assert r.code == 0, r.err
    assert "(1 user left)" in r.err
    r = cli("run", sealed, "--input", workdir / "x.npy", "--output", workdir / "y.npy", "--force",
            "--key-file", workdir / "k2.bin")  # fmt: skip
    assert r.code == 2 and "enrolled in nothing" in r.err  # the removed user's key opens nothing now
    y2_after, err = _run(cli, sealed, workdir, "--key-file", workdir / "k2.bin", "--allow-unenrolled-key")
    np.testing.assert_array_equal(y2_after, _original(workdir))
    y1_after, _ = _run(cli, sealed, workdir, "--key-file", workdir / "k.bin")
    np.testing.assert_array_equal(y1_after, y1)
    m = json.loads((sealed / C.MANIFEST).read_text())
    assert len(m[C.M_RECORDS]) == 1 and C.M_METRICS not in m
    assert sorted(p.name for p in (sealed / C.RECORDS_DIR).iterdir()) == sorted(first)
    bad = cli("remove-user", sealed, "--record", "nope")
    assert bad.code == 2 and m[C.M_RECORDS][0]["id"] in bad.err


def test_add_user_refuses_unsealed_bundles(cli, workdir):
    out = workdir / "open.prop"
    assert cli("personalize", workdir / "model.safetensors", "--data", workdir / "mine.npz",
               "--key-file", workdir / "k.bin", "--out", out, *FAST).code == 0  # fmt: skip
    r = cli("add-user", out, "--data", workdir / "mine.npz", "--key-file", workdir / "k2.bin")
    assert r.code == 2 and "sealed bundles" in r.err and len(r.err.strip().splitlines()) == 1


def test_passphrase_users(cli, workdir, monkeypatch):
    monkeypatch.setenv(C.ENV_PASSPHRASE, "correct horse battery staple")
    out = workdir / "pp.prop"
    r = cli("personalize", workdir / "model.safetensors", "--data", workdir / "mine.npz", "--passphrase",
            "--out", out, *SEALED)  # fmt: skip
    assert r.code == 0, r.err
    y_pp, _ = _run(cli, out, workdir, "--passphrase")
    monkeypatch.setenv(C.ENV_PASSPHRASE, "wrong horse")
    y_wrong, err = _run(cli, out, workdir, "--passphrase", "--allow-unenrolled-key")
    assert "enrolled in nothing" in err and np.abs(y_pp - y_wrong).max() > 1e-3


def test_sealed_export_runs_like_torch(cli, sealed, workdir):
    pytest.importorskip("onnxruntime")
    r = cli("export", sealed, "--onnx", "--key-file", workdir / "k.bin")
    assert r.code == 0, r.err
    assert not (sealed / C.EXPORT_DIR / C.POLICY_GRAPH).exists()  # no graph for a payload in the clear
    wrong = ["--key-file", workdir / "k2.bin", "--allow-unenrolled-key"]
    for key in ([], ["--key-file", workdir / "k.bin"], wrong):
        y_torch, _ = _run(cli, sealed, workdir, *key)
        y_onnx, _ = _run(cli, sealed, workdir, "--onnx", *key)
        np.testing.assert_allclose(y_onnx, y_torch, atol=1e-5)


def test_audit_of_a_sealed_bundle_tries_keys_on_the_records(cli, sealed, workdir):
    rep = workdir / "audit.json"
    r = cli("attack", sealed, "--data", workdir / "mine.npz", "--key-file", workdir / "k.bin",
            "--key-file", workdir / "k2.bin", "--blackbox", "3000", "--random", "64", "--per-distance", "8",
            "--restarts", "4", "--search-steps", "10", "--samples", "64", "--fewshot-restarts", "4",
            "--fewshot-steps", "20", "--max-leak", "0.01", "--json", rep)  # fmt: skip
    assert r.code == 0, r.err
    report = json.loads(rep.read_text())
    assert report["bundle"]["sealed"] and report["user"]["leakage"] > 0.5  # the user's key opens its record
    assert report["speed"]["blackbox"]["path"] == "sealed: trial decryption"
    assert report["speed"]["blackbox"]["scanned"] == 3000
    for g in report["groups"]:
        assert g["control"]["available"], g["name"]
        assert g["beyond"] == 0.0, g["name"]
        if g["kind"] == "key":  # every wrong key runs the original: nothing moves
            assert g["leakage"]["worst"] == 0.0 and g["fidelity"]["worst"] == 0.0, g["name"]
    assert report["max_leak"]["passed"]


def test_every_record_and_enrolment_is_tried_on_every_key(sealed, workdir, monkeypatch):
    """Records and enrolments without a lookup name (format 1-5; format 6 files each by name,
    tests/bundle/test_lookup.py): which one a key opens, or whether any does, sets no number of trial
    decryptions: each key tries every one, so the time does not tell which one opened
    (benchmarks/bench_open_timing.py measures it)."""
    from dataclasses import replace

    from prop_cli.bundle import enrol, records
    from prop_cli.bundle.records import SealedState, record_ad

    state = load_bundle(sealed).records
    user = read_key_file(workdir / "k.bin")
    rng = np.random.default_rng(3)
    others = [rng.integers(0, 2, 128).astype(np.uint8) for _ in range(2)]
    rec = replace(state.records[0], ciphertext=(sealed / state.manifest[C.M_RECORDS][0]["file"]).read_bytes(),
                  lookup=None)  # fmt: skip
    plaintext = open_record(rec, user, record_ad(state.manifest, rec.id))
    copies = [seal(plaintext, k, lambda rid: record_ad(state.manifest, rid)) for k in others]
    calls = []
    counted = records.open_record
    monkeypatch.setattr(records, "open_record", lambda *a: calls.append(1) or counted(*a))
    wrong = rng.integers(0, 2, 128).astype(np.uint8)
    for at in range(3):  # the user's record first, in the middle, last
        recs = copies[:at] + [rec] + copies[at:]
        three = SealedState(state.manifest, state.spec, recs)
        for bits, opens in [(user, rec.id), (others[0], recs[at + 1 if at == 0 else 0].id), (wrong, None)]:
            calls.clear()
            opened = three.open(bits)
            assert (opened.record_id if opened else None) == opens
            assert len(calls) == 3, (at, len(calls))
    entries = enrol.enrol(state.manifest, [others[0], user, others[1]])
    tried = []
    counted_decrypt = enrol.decrypt
    monkeypatch.setattr(enrol, "decrypt", lambda *a: tried.append(1) or counted_decrypt(*a))
    for bits, found in [(others[0], True), (others[1], True), (wrong, False)]:
        tried.clear()
        assert (enrol.open_enrolment(entries, bits) is not None) == found
        assert len(tried) == 3


def test_enrol_refuses_a_sealed_bundle_in_one_line(sealed, cli, workdir):
    """`prop enrol` is for unsealed bundles (the rule is the bundle's: write.enrol_key, Mode); a sealed
    bundle's users are enrolled in their own records, and the manifest is left as it was."""
    before = (sealed / "manifest.json").read_bytes()
    r = cli("enrol", sealed, "--key-file", workdir / "k.bin")
    assert r.code == 2 and "is sealed: each user is enrolled in their own record" in r.err
    assert "prop add-user" in r.err and "Traceback" not in r.err
    assert (sealed / "manifest.json").read_bytes() == before


def test_which_record_remove_user_deletes_is_the_bundles_rule(sealed, workdir):
    """records.record_to_remove: exactly one of a key and a record id; the key must open the record; an
    id must be the bundle's; never the last user. Each refusal is one line naming the fix."""
    from prop_cli.bundle.records import record_to_remove
    from prop_cli.errors import PropError

    b = load_bundle(sealed)
    key = read_key_file(workdir / "k.bin", b.key_bits)
    (rid,) = [e["id"] for e in b.manifest[C.M_RECORDS]]
    where = str(sealed)
    with pytest.raises(PropError, match="exactly one of --key-file/--passphrase and --record"):
        record_to_remove(b.manifest, b.records, None, None, where)
    with pytest.raises(PropError, match="exactly one"):
        record_to_remove(b.manifest, b.records, key, rid, where)
    with pytest.raises(PropError, match=rf"--record 'nope' is not in .*records: {rid}"):
        record_to_remove(b.manifest, b.records, None, "nope", where)
    with pytest.raises(PropError, match="opens no user's record"):
        record_to_remove(b.manifest, b.records, 1 - key, None, where)
    for bits, record in ((key, None), (None, rid)):  # found either way, then kept: the last user
        with pytest.raises(PropError, match=f"{rid} is the last user of .*delete the bundle folder"):
            record_to_remove(b.manifest, b.records, bits, record, where)
    two = {**b.manifest, C.M_RECORDS: [*b.manifest[C.M_RECORDS], {"id": "other"}]}
    assert record_to_remove(two, b.records, key, None, where) == rid
    assert record_to_remove(two, b.records, None, "other", where) == "other"
