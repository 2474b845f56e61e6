"""The ONNX export under whoever can write the files (issue 42, items 1 and 2): ``export.json`` read with
the manifest's schema and hostile-input rules, and every runner (`prop run --onnx`, ``OnnxRunner``,
``SealedOnnxRunner``) running the rollback check on the record or enrolment it actually opens. Each
attack is built as an attacker would: the genuine older files put back, or ``export.json`` edited with
its digest recomputed by prop's own functions."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

from prop_cli import constants as C
from prop_cli.bundle.manifest import stamp
from prop_cli.bundle.rollback import RollbackWarning
from prop_cli.core.key_files import read_key_file
from prop_cli.errors import PropError
from prop_cli.files import dump_json
from prop_cli.run import onnx as rt
from tests.conftest import FAST

pytest.importorskip("onnxruntime")


def _meta(folder: Path) -> dict:
    return json.loads((folder / C.EXPORT_META).read_text())


def _restamp(folder: Path, meta: dict) -> None:
    """export.json rewritten as an attacker would: its digest recomputed with prop's own function."""
    (folder / C.EXPORT_META).write_text(dump_json(stamp(meta, C.EXPORT_DIGEST)))


def _run_onnx(cli, bundle: Path, d: Path, key: str | None, *extra):
    out = d / "y.npy"
    out.unlink(missing_ok=True)
    args = ["--key-file", d / key] if key else []
    r = cli("run", bundle, "--onnx", "--input", d / "x.npy", "--output", out, "--json", *args, *extra)
    return r, (json.loads(r.out)["keyed"] if r.code == 0 else None)


def _one_line(r, *words: str) -> None:
    assert r.code == 2, (r.code, r.err)
    assert r.err.count("\n") == 1 and r.err.startswith("prop: error:"), r.err
    assert "Traceback" not in r.err
    for w in words:
        assert w in r.err, r.err


def _bits(d: Path, key: str) -> np.ndarray:
    return read_key_file(d / key, 128)


def _sealed(cli, d: Path) -> Path:
    """A sealed bundle of two users (k.bin, k2.bin), exported with k2's key bound."""
    from tests.bundle.test_rollback import _sealed_with_second_user

    b = _sealed_with_second_user(cli, d)
    r = cli("export", b, "--onnx", "--key-file", d / "k2.bin")
    assert r.code == 0, r.err
    return b


def _put_back(old: Path, folder: Path) -> None:
    """The attacker puts the genuine older onnx/ back in place: nothing restamped."""
    shutil.rmtree(folder)
    shutil.copytree(old, folder)


def test_an_older_export_put_back_after_re_enrolment_is_refused(cli, workdir):
    """Issue 42 finding 1: the user re-enrols (remove-user, add-user, export again); the attacker puts the
    older onnx/ back. 0.2.0: `run --onnx` ran the user's old record, exit 0, "keyed". Now refused in one
    line, with the bundle and by the standalone runner; --allow-rollback runs it standalone, warned."""
    b = _sealed(cli, workdir)
    r, keyed = _run_onnx(cli, b, workdir, "k2.bin")
    assert r.code == 0 and keyed, r.err
    old = workdir / "old-onnx"
    shutil.copytree(b / C.EXPORT_DIR, old)
    assert cli("remove-user", b, "--key-file", workdir / "k2.bin").code == 0
    r = cli("add-user", b, "--data", workdir / "mine.npz", "--key-file", workdir / "k2.bin", "--steps", "20")
    assert r.code == 0, r.err
    r = cli("export", b, "--onnx", "--key-file", workdir / "k2.bin", "--force")
    assert r.code == 0, r.err
    r, keyed = _run_onnx(cli, b, workdir, "k2.bin")
    assert r.code == 0 and keyed, r.err
    _put_back(old, b / C.EXPORT_DIR)
    r, _ = _run_onnx(cli, b, workdir, "k2.bin")
    _one_line(r, "older version of the bundle", "prop export")
    assert not (workdir / "y.npy").exists()
    for allow in ([], ["--allow-rollback"]):  # the export is not the bundle's: no option runs it
        _one_line(_run_onnx(cli, b, workdir, "k2.bin", *allow)[0])
    # The documented way to deploy: the export alone. The record it opens was removed here.
    with pytest.raises(PropError, match=r"older copy: the record this key opens was removed") as e:
        rt.SealedOnnxRunner(old, _bits(workdir, "k2.bin"))
    assert "--allow-rollback" in str(e.value) and "\n" not in str(e.value)
    with pytest.warns(RollbackWarning, match="running it anyway"):
        runner = rt.SealedOnnxRunner(old, _bits(workdir, "k2.bin"), allow_rollback=True)
    y = runner(np.load(workdir / "x.npy"))
    assert y.shape == (8, 2)


def test_an_older_export_put_back_after_removal_is_refused(cli, workdir):
    """The user is removed (remove-user updates the export in place); the older export is put back."""
    b = _sealed(cli, workdir)
    old = workdir / "old-onnx"
    shutil.copytree(b / C.EXPORT_DIR, old)
    assert cli("remove-user", b, "--key-file", workdir / "k2.bin").code == 0
    _put_back(old, b / C.EXPORT_DIR)
    _one_line(_run_onnx(cli, b, workdir, "k2.bin")[0])
    _one_line(_run_onnx(cli, b, workdir, "k2.bin", "--allow-unenrolled-key")[0], "older version")
    with pytest.raises(PropError, match=r"removed from it at version 3 on this machine"):
        rt.SealedOnnxRunner(old, _bits(workdir, "k2.bin"))
    with pytest.warns(RollbackWarning):
        rt.SealedOnnxRunner(old, _bits(workdir, "k2.bin"), allow_rollback=True)
    # Edited to claim a newer version (digest recomputed): the record was still removed here.
    meta = _meta(old)
    meta[C.M_BUNDLE_VERSION] = 99
    _restamp(old, meta)
    with pytest.raises(PropError, match=r"removed from it at version 3"):
        rt.SealedOnnxRunner(old, _bits(workdir, "k2.bin"))
    # The export as remove-user left it: current, the remaining user runs, the removed one is refused.
    r, keyed = _run_onnx(cli, b, workdir, "k.bin")
    _one_line(r)  # the old export (version 99 now) is still not this bundle's
    shutil.rmtree(b / C.EXPORT_DIR)
    assert cli("export", b, "--onnx", "--key-file", workdir / "k.bin").code == 0
    assert _run_onnx(cli, b, workdir, "k.bin")[1] is True


def test_the_export_follows_every_write_of_its_bundle(cli, workdir):
    """add-user, remove-user and a recorded audit write a new bundle version: the export in <bundle>/onnx
    takes it with them, so that it stays the bundle's (and a key bound to it keeps running)."""
    b = _sealed(cli, workdir)
    folder = b / C.EXPORT_DIR
    version = lambda: json.loads((b / C.MANIFEST).read_text())[C.M_BUNDLE_VERSION]  # noqa: E731
    assert _meta(folder)[C.M_BUNDLE_VERSION] == version() == 2
    r = cli("attack", b, "--key-file", workdir / "k2.bin", "--data", workdir / "mine.npz", "--probes", "null",
            "--record")  # fmt: skip
    assert r.code in (0, 1), r.err
    assert _meta(folder)[C.M_BUNDLE_VERSION] == version() == 3
    assert _run_onnx(cli, b, workdir, "k2.bin")[1] is True
    assert rt.SealedOnnxRunner(folder, _bits(workdir, "k2.bin")).opened is not None
    assert cli("remove-user", b, "--key-file", workdir / "k.bin").code == 0
    assert _meta(folder)[C.M_BUNDLE_VERSION] == version() == 4
    assert _run_onnx(cli, b, workdir, "k2.bin")[1] is True


def test_an_unsealed_export_bound_to_an_older_enrolment_is_refused_alone(cli, workdir):
    """Unsealed: the owner updates the bundle and the user accepts it (prop enrol: enrolment version 2);
    the export bound to the user's older enrolment is refused by ``OnnxRunner`` on this machine."""
    from tests.bundle.test_rollback import _owner_update

    b = workdir / "u.prop"
    r = cli("personalize", workdir / "model.safetensors", "--data", workdir / "mine.npz",
            "--key-file", workdir / "k.bin", "--out", b, *FAST)  # fmt: skip
    assert r.code == 0, r.err
    assert cli("export", b, "--onnx", "--key-file", workdir / "k.bin").code == 0
    old = workdir / "old-onnx"
    shutil.copytree(b / C.EXPORT_DIR, old)
    assert rt.OnnxRunner(old, _bits(workdir, "k.bin")) is not None
    _owner_update(b)
    r = cli("enrol", b, "--key-file", workdir / "k.bin")
    assert r.code == 0 and "re-enrolled" in r.out, r.out + r.err
    with pytest.raises(PropError, match=r"enrolment of version 1, and this machine has seen its enrolment"):
        rt.OnnxRunner(old, _bits(workdir, "k.bin"))
    with pytest.warns(RollbackWarning):
        rt.OnnxRunner(old, _bits(workdir, "k.bin"), allow_rollback=True)


# ---- export.json's schema -----------------------------------------------------------------------


@pytest.fixture(scope="module")
def exports(tmp_path_factory) -> dict[str, Path]:
    """A sealed and an unsealed bundle of one user, each exported with the user's key bound."""
    from prop_cli.api import KeySource, personalize_checkpoint
    from prop_cli.bundle import load_bundle
    from prop_cli.config import PersonalizeConfig
    from tests.conftest import make_mlp_checkpoint

    root = tmp_path_factory.mktemp("exports")
    make_mlp_checkpoint(root / "model.safetensors")
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (200, 4)).astype(np.float32)
    np.savez(root / "mine.npz", x=x, y=(-x[:, :2] * 0.5).astype(np.float32))
    np.save(root / "x.npy", x[:8])
    (root / "k.bin").write_bytes(rng.integers(0, 256, 16, dtype=np.uint8).tobytes())
    (root / "k.bin").chmod(0o600)
    bits = _bits(root, "k.bin")
    out = {}
    for mode, seal in (("unsealed", False), ("sealed", True)):
        b = root / f"{mode}.prop"
        cfg = PersonalizeConfig.of(steps=30, seal=seal)
        users = [(root / "mine.npz", KeySource(bits, "file"))]
        personalize_checkpoint(str(root / "model.safetensors"), users, b, cfg)
        assert rt.export_onnx(load_bundle(b), key=bits).ok
        out[mode] = b
    return out


@pytest.mark.parametrize("mode", ["sealed", "unsealed"])
def test_a_record_or_graph_outside_the_export_is_refused(cli, tmp_path, exports, mode):
    """0.2.0: a record path such as /anywhere/users/<id>.sealed was read from outside the export (run
    --onnx exit 0, keyed); a graph name with a folder in it was hashed and opened too."""
    src = exports[mode]
    b = tmp_path / src.name
    shutil.copytree(src, b)
    folder = b / C.EXPORT_DIR
    meta = _meta(folder)
    outside = tmp_path / "anywhere"
    if mode == "sealed":
        rec = meta["sealed"][C.M_RECORDS][0]
        (outside / C.RECORDS_DIR).mkdir(parents=True)
        shutil.copyfile(folder / rec["file"], outside / rec["file"])
        rec["file"] = str(outside / rec["file"])
        field = "sealed.records[0].file"
    else:
        outside.mkdir()
        shutil.copyfile(folder / C.BASE_GRAPH, outside / C.BASE_GRAPH)
        meta["graphs"][f"../../anywhere/{C.BASE_GRAPH}"] = meta["graphs"].pop(C.BASE_GRAPH)
        field = f"graphs.../../anywhere/{C.BASE_GRAPH}"
    _restamp(folder, meta)
    r = cli("run", b, "--onnx", "--key-file", src.parent / "k.bin", "--input", src.parent / "x.npy",
            "--output", tmp_path / "y.npy")  # fmt: skip
    _one_line(r, f"field '{field}'")
    runner = rt.SealedOnnxRunner if mode == "sealed" else rt.OnnxRunner
    with pytest.raises(PropError, match="field"):
        runner(folder, _bits(src.parent, "k.bin"))


def test_inspect_of_a_hostile_export_says_why_it_is_not_current(cli, tmp_path, exports):
    """0.2.0: `prop inspect` of a bundle whose export.json says "sealed": "x" (digest recomputed) ended in
    an AttributeError, with no key given."""
    b = tmp_path / "b.prop"
    shutil.copytree(exports["sealed"], b)
    meta = _meta(b / C.EXPORT_DIR)
    meta["sealed"] = "x"
    _restamp(b / C.EXPORT_DIR, meta)
    r = cli("inspect", b, "--json")
    assert r.code == 0, r.err
    export = json.loads(r.out)["onnx_export"]
    assert export["current"] is False and "field 'sealed' must be an object" in export["why"], export


def test_links_inside_an_export_are_refused(tmp_path, exports):
    """users/ or a graph linked to files elsewhere: refused in one line naming the link."""
    for mode, rel in (("sealed", C.RECORDS_DIR), ("unsealed", C.ENCODER_GRAPH)):
        folder = tmp_path / mode
        shutil.copytree(exports[mode] / C.EXPORT_DIR, folder)
        elsewhere = tmp_path / f"{mode}-elsewhere"
        shutil.move(folder / rel, elsewhere)
        (folder / rel).symlink_to(elsewhere)
        runner = rt.SealedOnnxRunner if mode == "sealed" else rt.OnnxRunner
        with pytest.raises(PropError, match=f"{rel} is a symbolic link"):
            runner(folder, _bits(exports[mode].parent, "k.bin"))


# Values a one-field edit puts in place of a JSON value: wrong types, edges, junk, paths.
_ODD = [None, True, False, 0, -1, 1, 7, 2**31, 2**64, -(2**63), 0.5, -1e308, 1e308, "", "x", "relu",
        "../../etc/passwd", "/etc/passwd", "0" * 64, "users/x.sealed", "base.onnx", [], [1], [None], {},
        {"a": 1}, [[[]]], "NaN"]  # fmt: skip


def _paths(value, here=()) -> list[tuple]:
    """Every field and item of a JSON value, as paths of keys and indices (the value itself first)."""
    out = [here]
    if isinstance(value, dict):
        for k, v in value.items():
            out += _paths(v, (*here, k))
    elif isinstance(value, list):
        for i, v in enumerate(value[:3]):
            out += _paths(v, (*here, i))
    return out


def _mutated(meta: dict, path: tuple, how: str, new) -> dict:
    meta = json.loads(json.dumps(meta))
    *parents, last = path
    node = meta
    for p in parents:
        node = node[p]
    if how == "delete":
        del node[last]
    elif how == "add" and isinstance(node[last], dict):
        node[last]["zz_unknown"] = new
    else:
        node[last] = new
    return meta


def _outcome(fn) -> str:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            fn()
        except PropError as e:
            assert "\n" not in e.line(), e.line()
            return "refused"
    return "ran"


@pytest.mark.parametrize("mode", ["sealed", "unsealed"])
def test_one_field_edits_of_export_json_run_or_are_refused_in_one_line(tmp_path, exports, mode):
    """0.2.0: 30 distinct tracebacks in 600 fuzzed runs. Every field and item of export.json replaced by
    an odd value, deleted, or given an unknown neighbour, the digest recomputed: with the key, without it,
    with the bundle (`run --onnx`) and alone, and `prop inspect`'s reading: each runs or is a PropError."""
    from prop_cli.bundle import load_bundle

    src = exports[mode]
    folder = tmp_path / "onnx"
    shutil.copytree(src / C.EXPORT_DIR, folder)
    original = _meta(folder)
    del original[C.EXPORT_DIGEST]
    bits = _bits(src.parent, "k.bin")
    x = np.load(src.parent / "x.npy")
    bundle = load_bundle(src)
    runner = rt.SealedOnnxRunner if mode == "sealed" else rt.OnnxRunner
    rng = np.random.default_rng(42)
    paths = [p for p in _paths(original) if p]
    cases = [(p, "delete", None) for p in paths] + [(p, "add", 1) for p in paths]
    cases += [(p, "set", _ODD[int(rng.integers(len(_ODD)))]) for p in paths for _ in range(3)]
    seen: dict[str, int] = {}
    for path, how, new in cases:
        try:
            meta = _mutated(original, path, how, new)
        except (KeyError, TypeError, IndexError):
            continue
        _restamp(folder, meta)
        for name, fn in (
            ("inspect", lambda: rt.describe_export(folder, bundle.manifest)),
            ("keyed", lambda: runner(folder, bits)(x)),
            ("no key", lambda: runner(folder)(x)),
            ("bundle", lambda: rt.run_onnx(bundle, x, bits, folder)),
        ):
            try:
                got = _outcome(fn)
            except Exception as e:  # noqa: BLE001 - what the test is for: name the case
                raise AssertionError(f"{path} {how} {new!r} ({name}): {type(e).__name__}: {e}") from e
            seen[got] = seen.get(got, 0) + 1
    assert seen.get("refused", 0) > len(cases), seen  # most edits are refused; the rest ran
