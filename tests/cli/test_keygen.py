"""prop keygen (prop_cli/cli/keygen_cmd.py) and the key files it writes."""

from __future__ import annotations

import json

import pytest


def test_a_missing_key_file_names_the_flag(tmp_path):
    from prop_cli.core.key_files import read_key_file
    from prop_cli.errors import PropError

    for path in (tmp_path / "missing.bin", tmp_path):
        with pytest.raises(PropError, match="--key-file"):
            read_key_file(path)


def test_keygen_and_inspect(cli, workdir):
    res = cli("keygen", workdir / "new.bin", "--bits", "256")
    assert res.code == 0
    assert (workdir / "new.bin").stat().st_size == 32
    assert (workdir / "new.bin").stat().st_mode & 0o777 == 0o600
    res = cli("inspect", workdir / "model.safetensors", "--json")
    info = json.loads(res.out)
    assert [(la["name"], la["keyed"]) for la in info["layers"]] == [
        ("0", False),
        ("2", True),
        ("4", True),
    ]
    res = cli("inspect", workdir / "model.safetensors", "--layers", "4", "--json")
    assert [la["keyed"] for la in json.loads(res.out)["layers"]] == [False, False, True]
