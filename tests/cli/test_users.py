"""prop add-user (prop_cli/cli/users_cmd.py)."""

from __future__ import annotations

import json

import pytest

from tests.cli.shares import assert_clean_error, personalize


def test_add_user_checks_the_bundle_is_writable_before_training(cli, workdir, monkeypatch):
    import tempfile

    import prop_cli.api as api

    out = workdir / "sealed.prop"
    assert personalize(cli, workdir, "--seal", "--steps", "5", out="sealed.prop").code == 0
    calls: list = []
    monkeypatch.setattr(api, "train_added_user", lambda *a, **kw: calls.append("train"))

    def refuse(*a, **kw):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    res = cli("add-user", out, "--data", workdir / "mine.npz", "--key-file", workdir / "k2.bin")
    assert_clean_error(res, "cannot be written in place")
    assert not calls


def test_a_sealed_bundles_recorded_harden_is_dropped_for_add_user(cli, workdir):
    """Sealed bundles written before --seal --harden was refused recorded --harden's settings untrained;
    add-user reads them without them instead of refusing its own bundle."""
    from types import SimpleNamespace

    from prop_cli.config import PersonalizeConfig
    from prop_cli.errors import PropError
    from prop_cli.train.added_user import added_user_config

    out = workdir / "sealed.prop"
    assert personalize(cli, workdir, "--seal", "--steps", "5", out="sealed.prop").code == 0
    m = json.loads((out / "manifest.json").read_text())
    m["config"] |= {"harden": True, "code_negatives": 64, "encoder_init": "os", "antipode_codes": 16}
    cfg = added_user_config(SimpleNamespace(manifest=m, key_bits=128), None)
    assert cfg.sealed and "harden" not in cfg.to_dict() and "code_negatives" not in cfg.to_dict()
    with pytest.raises(PropError, match="sealed bundle trains none"):  # the same settings, given anew
        PersonalizeConfig.of(**m["config"])
