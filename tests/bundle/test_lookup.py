"""Format 6: a key finds its own record or enrolment by its lookup name (issue 39), the same work for
every key; older bundles still open by trying every record. Timings: benchmarks/bench_lookup.py."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from prop_cli import constants as C
from prop_cli.api import load_bundle, read_key_file
from prop_cli.bundle import records
from prop_cli.bundle.cipher import lookup_name
from prop_cli.bundle.manifest import next_version, stamp
from prop_cli.bundle.records import rewrite_records, seal_payload, with_records
from prop_cli.errors import PropError
from prop_cli.files import dump_json
from tests.conftest import FAST

USERS = 5


def _keys(n: int, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 2, 128).astype(np.uint8) for _ in range(n)]


def _add_users(bundle: Path, user: np.ndarray, keys: list[np.ndarray]) -> None:
    """What add-user writes for ``keys`` (records sealed against the next version, one manifest write),
    with the first user's payload for each: no training."""
    b = load_bundle(bundle)
    opened = b.records.open(user)
    m = b.manifest
    recs = [seal_payload(next_version(m), opened.meta, opened.payload, k) for k in keys]
    rewrite_records(bundle, m, with_records(m, recs, []), recs)


@pytest.fixture
def many(cli, workdir) -> tuple[Path, list[np.ndarray]]:
    """A sealed bundle of USERS users: the workdir's key first, then USERS - 1 more."""
    out = workdir / "many.prop"
    r = cli("personalize", workdir / "model.safetensors", "--data", workdir / "mine.npz",
            "--key-file", workdir / "k.bin", "--out", out, *FAST, "--seal")  # fmt: skip
    assert r.code == 0, r.err
    keys = [read_key_file(workdir / "k.bin"), *_keys(USERS - 1, 1)]
    _add_users(out, keys[0], keys[1:])
    return out, keys


def _counted(monkeypatch) -> list[int]:
    calls: list[int] = []
    real = records.open_record
    monkeypatch.setattr(records, "open_record", lambda *a: calls.append(1) or real(*a))
    return calls


def _manifest(bundle: Path) -> dict:
    return json.loads((bundle / C.MANIFEST).read_text())


def test_a_key_opens_its_own_record_among_several_with_one_trial(many, monkeypatch):
    bundle, keys = many
    m = _manifest(bundle)
    assert m[C.M_FORMAT] == C.FORMAT_VERSION == 6 and len(m[C.M_RECORDS]) == USERS
    names = [e[C.M_LOOKUP] for e in m[C.M_RECORDS]]
    assert names == [lookup_name(k, m[C.M_BUNDLE_ID]) for k in keys]  # filed under their keys' names
    state = load_bundle(bundle).records
    calls = _counted(monkeypatch)
    wrong = _keys(1, 99)[0]
    for i in (0, USERS // 2, USERS - 1, None):  # first, middle, last, enrolled in nothing
        calls.clear()
        opened = state.open(keys[i] if i is not None else wrong)
        assert (opened.record_id if opened else None) == (m[C.M_RECORDS][i]["id"] if i is not None else None)
        assert len(calls) == 1  # one record tried, found or a stand-in: the same work for every key
        if opened is not None:
            assert opened.changed == [] and opened.version == (1 if i == 0 else 2)
    near = keys[2].copy()
    near[0] ^= 1
    assert state.open(near) is None


def test_a_key_enrolled_in_nothing_is_refused_as_before(cli, many, workdir):
    bundle, _ = many
    (workdir / "wrong.bin").write_bytes(bytes(range(16)))
    (workdir / "wrong.bin").chmod(0o600)
    r = cli("run", bundle, "--input", workdir / "x.npy", "--output", workdir / "y.npy",
            "--key-file", workdir / "wrong.bin")  # fmt: skip
    assert r.code == 2 and "enrolled in nothing" in r.err and r.err.count("\n") == 1
    assert not (workdir / "y.npy").exists()
    r = cli("run", bundle, "--input", workdir / "x.npy", "--output", workdir / "y.npy",
            "--key-file", workdir / "k.bin")  # fmt: skip
    assert r.code == 0, r.err


def test_names_say_nothing_of_the_key_without_it(many, cli, workdir):
    """A name is a keyed hash under the bundle id: not the key, not its plain hash, and another under
    another bundle id (the same key personalized again); the file names stay random ids."""
    bundle, keys = many
    m = _manifest(bundle)
    key = (workdir / "k.bin").read_bytes()
    plain = {key.hex(), hashlib.sha256(key).hexdigest(), hashlib.sha256(key).hexdigest()[:32]}
    entry = m[C.M_RECORDS][0]
    assert entry[C.M_LOOKUP] not in plain and entry[C.M_LOOKUP] not in entry["file"]
    assert entry["file"] == f"{C.RECORDS_DIR}/{entry['id']}{C.RECORD_SUFFIX}"
    again = workdir / "again.prop"
    r = cli("personalize", workdir / "model.safetensors", "--data", workdir / "mine.npz",
            "--key-file", workdir / "k.bin", "--out", again, *FAST, "--seal")  # fmt: skip
    assert r.code == 0, r.err
    assert _manifest(again)[C.M_RECORDS][0][C.M_LOOKUP] != entry[C.M_LOOKUP]


def _as_format_5(bundle: Path) -> dict:
    """The bundle as prop wrote format 5 (the code before issue 39): the same records, no names."""
    m = _manifest(bundle)
    m[C.M_FORMAT] = 5
    for e in m[C.M_RECORDS]:
        del e[C.M_LOOKUP]
    (bundle / C.MANIFEST).write_text(dump_json(stamp(m)))
    return m


def test_a_format_5_bundle_opens_by_trying_every_record(many, monkeypatch, cli, workdir):
    bundle, keys = many
    m = _as_format_5(bundle)
    state = load_bundle(bundle).records
    calls = _counted(monkeypatch)
    for i, k in enumerate(keys):
        calls.clear()
        assert state.open(k).record_id == m[C.M_RECORDS][i]["id"]
        assert len(calls) == USERS  # every record, whichever opens
    assert state.open(_keys(1, 99)[0]) is None
    # add-user keeps it format 5: the new record has no name (the others' cannot be added without keys)
    monkeypatch.undo()
    new = _keys(1, 7)[0]
    _add_users(bundle, keys[0], [new])
    m = _manifest(bundle)
    assert m[C.M_FORMAT] == 5 and not any(C.M_LOOKUP in e for e in m[C.M_RECORDS])
    assert load_bundle(bundle).records.open(new).record_id == m[C.M_RECORDS][-1]["id"]
    r = cli("run", bundle, "--input", workdir / "x.npy", "--output", workdir / "y.npy",
            "--key-file", workdir / "k.bin")  # fmt: skip
    assert r.code == 0, r.err


def test_prop_0_1_sealed_bundles_open_by_trying_every_record(monkeypatch, workdir):
    from tests.fixtures import v01

    fx = v01.load("mlp-sealed-lora")  # format 4, three users
    state = load_bundle(fx.bundle).records
    calls = _counted(monkeypatch)
    for name in ("k.bin", "k2.bin"):
        calls.clear()
        assert state.open(read_key_file(fx.key(name, workdir))) is not None
        assert len(calls) == len(state.records) == 3


def test_add_user_refuses_a_key_already_filed(many, workdir):
    from prop_cli.bundle.records import check_new_key

    bundle, keys = many
    state = load_bundle(bundle).records
    with pytest.raises(PropError, match="already opens a user"):
        check_new_key(state, keys[3])
    check_new_key(state, _keys(1, 5)[0])


def test_two_entries_under_one_name_are_refused(many, cli):
    bundle, _ = many
    m = _manifest(bundle)
    m[C.M_RECORDS][1][C.M_LOOKUP] = m[C.M_RECORDS][0][C.M_LOOKUP]
    (bundle / C.MANIFEST).write_text(dump_json(stamp(m)))
    r = cli("inspect", bundle)
    assert r.code == 2 and "field 'records' files two entries under the same lookup name" in r.err


def test_a_damaged_record_stops_only_its_own_key(many, cli, workdir):
    """Format 6 reads a record when a key tries it: another user's damaged record does not stop yours;
    your own is refused (sha256), and so is the bundle in inspect, which checks every record."""
    bundle, keys = many
    m = _manifest(bundle)
    rec = bundle / m[C.M_RECORDS][1]["file"]
    rec.write_bytes(rec.read_bytes()[:-1] + b"\0")
    state = load_bundle(bundle).records
    assert state.open(keys[0]) is not None
    with pytest.raises(PropError, match="does not match its sha256"):
        state.open(keys[1])
    assert cli("inspect", bundle).code == 2


def test_unsealed_enrolments_are_filed_by_name(cli, workdir, monkeypatch):
    """Unsealed format 6: each enrolment under its key's name, one opened per key; `prop enrol` on a
    format 5 bundle files the new enrolment by name and keeps the others (tried on every key)."""
    from prop_cli.bundle import enrol

    out = workdir / "u.prop"
    r = cli("personalize", workdir / "model.safetensors", "--data", workdir / "mine.npz",
            "--key-file", workdir / "k.bin", "--data", workdir / "mine.npz", "--key-file", workdir / "k2.bin",
            "--out", out, *FAST)  # fmt: skip
    assert r.code == 0, r.err
    m = _manifest(out)
    k, k2 = read_key_file(workdir / "k.bin"), read_key_file(workdir / "k2.bin")
    assert [e[C.M_LOOKUP] for e in m[C.M_ENROLMENTS]] == [lookup_name(x, m[C.M_BUNDLE_ID]) for x in (k, k2)]
    tried: list[int] = []
    real = enrol.decrypt
    monkeypatch.setattr(enrol, "decrypt", lambda *a: tried.append(1) or real(*a))
    mode = load_bundle(out).mode
    for bits, ok in ((k, True), (k2, True), (_keys(1, 3)[0], False)):
        tried.clear()
        assert mode.enrolled(bits) is ok and len(tried) == 1
    monkeypatch.undo()
    for e in m[C.M_ENROLMENTS]:
        del e[C.M_LOOKUP]
    m[C.M_FORMAT] = 5
    (out / C.MANIFEST).write_text(dump_json(stamp(m)))
    assert load_bundle(out).mode.enrolled(k2)
    (workdir / "k3.bin").write_bytes(bytes(range(16)))
    (workdir / "k3.bin").chmod(0o600)
    r = cli("enrol", out, "--key-file", workdir / "k3.bin")
    assert r.code == 0 and "format 6" in r.out, r.err
    entries = _manifest(out)[C.M_ENROLMENTS]
    assert [C.M_LOOKUP in e for e in entries] == [False, False, True]
    mode = load_bundle(out).mode
    assert all(mode.enrolled(read_key_file(workdir / n)) for n in ("k.bin", "k2.bin", "k3.bin"))
    assert not mode.enrolled(_keys(1, 3)[0])


def test_the_sealed_onnx_export_opens_by_name(many, workdir, monkeypatch):
    """SealedOnnxRunner opens the record the key is filed under (export.json carries the names)."""
    pytest.importorskip("onnxruntime")
    from prop_cli.api import export_bundle
    from prop_cli.run.onnx.sealed import SealedOnnxRunner

    bundle, keys = many
    folder, kf = workdir / "onnx", workdir / "k4.bin"
    kf.write_bytes(np.packbits(keys[3]).tobytes())
    kf.chmod(0o600)
    export_bundle(bundle, folder, key_file=kf)
    calls = _counted(monkeypatch)
    x = np.load(workdir / "x.npy")
    y = SealedOnnxRunner(folder, keys[3])(x)
    assert len(calls) == 1 and y.shape == (8, 2)
    with pytest.raises(PropError, match="not bound"):
        SealedOnnxRunner(folder, keys[1])
    shutil.rmtree(folder)
