"""`prop inspect BUNDLE`: a bundle described from its checked manifest, without a key or any import."""

from __future__ import annotations

import json

import numpy as np

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
    assert [x["name"] for x in u["keyed_layers"]] == ["2", "4"] and u["audit"] is None and not u["signed"]
    s = json.loads(cli("inspect", tmp_path / "s", "--json").out)
    assert s["mode"] == "sealed" and s["records"] == 2 and s["payload"]["kind"] == "lora"

    r = cli("attack", tmp_path / "u", "--data", tmp_path / "mine.npz", "--key-file", tmp_path / "k.bin",
            "--probes", "null,random", "--random", "8", "--max-leak", "0.99", "--record")  # fmt: skip
    assert r.code in (0, 1), r.err
    (tmp_path / "u" / C.SIGNATURE_FILE).write_bytes(b"{}")  # presence only: prop verify checks it
    u = json.loads(cli("inspect", tmp_path / "u", "--json").out)
    assert u["audit"]["max_leak"]["threshold"] == 0.99 and u["signed"]
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
