"""`prop inspect BUNDLE`: a bundle described from its checked manifest, without a key or any import."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from prop_cli import constants as C
from tests.conftest import FAST, write_keys, write_user_data


def test_inspect_describes_unsealed_and_sealed_bundles_and_their_audit(tmp_path, cli):
    rng = np.random.default_rng(0)
    write_user_data(tmp_path, 80, rng)
    write_keys(tmp_path, ("k.bin", "k2.bin"), rng)
    common = ["--data", tmp_path / "mine.npz", "--key-file", tmp_path / "k.bin", *FAST]
    assert cli("personalize", tmp_path / "model.safetensors", *common, "--out", tmp_path / "u").code == 0
    r = cli("personalize", tmp_path / "model.safetensors", *common, "--out", tmp_path / "s", "--seal")
    assert r.code == 0, r.err
    r = cli("add-user", tmp_path / "s", "--data", tmp_path / "mine.npz", "--key-file", tmp_path / "k2.bin")
    assert r.code == 0, r.err

    u = json.loads(cli("inspect", tmp_path / "u", "--json").out)
    assert u["mode"] == "unsealed" and u["users"] == 1 and u["key_bits"] == 128
    assert [x["name"] for x in u["keyed_layers"]] == ["2", "4"]
    assert u["audit"] is None and u["signature"] is None
    s = json.loads(cli("inspect", tmp_path / "s", "--json").out)
    assert s["mode"] == "sealed" and s["records"] == 2 and s["payload"]["kind"] == "lora"

    r = cli("attack", tmp_path / "u", "--data", tmp_path / "mine.npz", "--key-file", tmp_path / "k.bin",
            "--probes", "null,random", "--random", "8", "--max-leak", "0.99", "--record")  # fmt: skip
    assert r.code in (0, 1), r.err
    (tmp_path / "u" / C.SIGNATURE_FILE).write_bytes(b"{}")  # presence only: prop verify checks it
    u = json.loads(cli("inspect", tmp_path / "u", "--json").out)
    assert u["audit"]["max_leak"]["threshold"] == 0.99
    assert u["audit"]["probes"] == ["null", "random"] and not u["audit"]["passed"]  # not the default probes
    assert u["signature"] == "present, not verified (model.sig: prop verify checks it)"
    table = cli("inspect", tmp_path / "u")
    assert table.code == 0 and "unsealed bundle" in table.out and "--max-leak 0.99" in table.out
    assert "1 enrolled user" in table.out and "1 enrolled users" not in table.out
    # Nothing of either key is printed (bundles hold none; the description reads only the manifest).
    for name in ("k.bin", "k2.bin"):
        k = (tmp_path / name).read_bytes()
        for out in (table.out, json.dumps(u), json.dumps(s)):
            assert k.hex() not in out


def test_a_changed_file_is_one_line(tmp_path, cli):
    rng = np.random.default_rng(1)
    write_user_data(tmp_path, 60, rng)
    write_keys(tmp_path, ("k.bin",), rng)
    r = cli("personalize", tmp_path / "model.safetensors", "--data", tmp_path / "mine.npz", "--key-file",
            tmp_path / "k.bin", "--out", tmp_path / "u", *FAST)  # fmt: skip
    assert r.code == 0, r.err
    with open(tmp_path / "u" / C.BASE_WEIGHTS, "ab") as f:
        f.write(b"\0")
    r = cli("inspect", tmp_path / "u")
    assert r.code == 2 and "does not match its sha256" in r.err and len(r.err.strip().splitlines()) == 1


def _row(table: str, name: str) -> str:
    """The value cell of the row ``name`` of `prop inspect`'s table."""
    cells = next(line for line in table.splitlines() if f" {name} " in line).split("│")
    return cells[2].strip()


def _sealed(tmp_path, cli, seed: int):
    rng = np.random.default_rng(seed)
    write_user_data(tmp_path, 60, rng)
    write_keys(tmp_path, ("k.bin", "k2.bin"), rng)
    r = cli("personalize", tmp_path / "model.safetensors", "--data", tmp_path / "mine.npz", "--key-file",
            tmp_path / "k.bin", "--out", tmp_path / "s", "--seal", *FAST)  # fmt: skip
    assert r.code == 0, r.err
    return tmp_path / "s"


def test_a_sealed_bundle_copied_without_its_records_is_incomplete(tmp_path, cli):
    s = _sealed(tmp_path, cli, 2)
    r = cli("add-user", s, "--data", tmp_path / "mine.npz", "--key-file", tmp_path / "k2.bin", *FAST)
    assert r.code == 0, r.err
    whole = cli("inspect", s)
    files = len(json.loads((s / C.MANIFEST).read_text())[C.M_FILES]) + 2  # and the two records
    assert whole.code == 0 and _row(whole.out, "key") == "128 bits; 2 records"
    assert _row(whole.out, "files") == f"{files}, every sha256 checked"
    first = sorted((s / C.RECORDS_DIR).iterdir())[0]
    first.unlink()
    r = cli("inspect", s)
    assert r.code == 2 and not r.out and len(r.err.strip().splitlines()) == 1
    assert "incomplete: 1 of 2 user records missing" in r.err and first.name in r.err
    shutil.rmtree(s / C.RECORDS_DIR)  # copied without users/
    np.save(tmp_path / "x.npy", np.zeros((2, 4), np.float32))
    run = ["run", s, "--input", tmp_path / "x.npy", "--output", tmp_path / "y.npy"]
    for args in (["inspect", s], ["inspect", s, "--json"], run):
        r = cli(*args)
        assert r.code == 2 and "incomplete: 2 of 2 user records missing" in r.err, args


def test_inspect_tells_whether_the_onnx_export_matches_the_bundle(tmp_path, cli):
    pytest.importorskip("onnxruntime")
    s = _sealed(tmp_path, cli, 3)
    assert json.loads(cli("inspect", s, "--json").out)["onnx_export"] is None
    assert _row(cli("inspect", s).out, "onnx export") == "no"
    r = cli("export", s, "--onnx", "--key-file", tmp_path / "k.bin")
    assert r.code == 0, r.err
    e = json.loads(cli("inspect", s, "--json").out)["onnx_export"]
    assert e["current"] and e["records"] == 1 and e["bound_keys"] == 1
    assert _row(cli("inspect", s).out, "onnx export").endswith("(1 user record, 1 key bound)")

    # add-user puts the new record in the export (as remove-user takes one out) and says so.
    r = cli("add-user", s, "--data", tmp_path / "mine.npz", "--key-file", tmp_path / "k2.bin", *FAST)
    assert r.code == 0 and "now holds the new record" in r.err and "--key-file KEY" in r.err
    e = json.loads(cli("inspect", s, "--json").out)["onnx_export"]
    assert e["current"] and e["records"] == 2 and e["bound_keys"] == 1
    x = tmp_path / "x.npy"
    np.save(x, np.random.default_rng(0).uniform(-1, 1, (4, 4)).astype(np.float32))
    torch_run = cli("run", s, "--input", x, "--key-file", tmp_path / "k2.bin", "--output", tmp_path / "t.npy")
    assert torch_run.code == 0, torch_run.err
    # The first user's key stays bound; the new one is named as not bound (not run as the base).
    onnx = ["run", s, "--onnx", "--input", x, "--output", tmp_path / "o.npy", "--force", "--key-file"]
    assert cli(*onnx, tmp_path / "k.bin").code == 0
    r = cli(*onnx, tmp_path / "k2.bin")
    assert r.code == 2 and "not bound to this key" in r.err
    r = cli("export", s, "--onnx", "--key-file", tmp_path / "k2.bin", "--force")
    assert r.code == 0, r.err
    r = cli(*onnx, tmp_path / "k2.bin")
    assert r.code == 0, r.err
    np.testing.assert_allclose(np.load(tmp_path / "o.npy"), np.load(tmp_path / "t.npy"), atol=1e-5)

    # An export that does not match (here: its export.json edited) is reported, and add-user leaves it be.
    meta = s / C.EXPORT_DIR / C.EXPORT_META
    (s / C.EXPORT_DIR / C.EXPORT_META).write_text(meta.read_text().replace('"graphs"', '"graphs" ', 1))
    e = json.loads(cli("inspect", s, "--json").out)["onnx_export"]
    assert not e["current"] and e["why"] and "prop export" in e["fix"]
    assert _row(cli("inspect", s).out, "onnx export").startswith("STALE")
    before = meta.read_bytes()
    write_keys(tmp_path, ("k3.bin",), np.random.default_rng(9))
    r = cli("add-user", s, "--data", tmp_path / "mine.npz", "--key-file", tmp_path / "k3.bin", *FAST)
    assert r.code == 0 and "no longer matches the bundle" in r.err and meta.read_bytes() == before
