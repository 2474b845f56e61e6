"""Hardened unsealed mode (--harden): its preset, code-space negatives, the unrecorded encoder init."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from prop_adapters import load_checkpoint
from prop_cli.config import HARDENED, PLAIN, Hardening, PersonalizeConfig, SealedConfig, UnsealedConfig
from prop_cli.core.keyed_model import KeyEncoder
from prop_cli.datasources import Dataset
from prop_cli.errors import PropError
from prop_cli.train import User, personalize
from prop_cli.train.hardening import code_negatives, encoder_init
from tests.conftest import make_mlp_checkpoint


def _preset(cfg: PersonalizeConfig) -> tuple:
    h = cfg.mode.hardening
    return h.encoder_init, h.code_negatives, h.antipode_codes


def test_preset_is_a_value_and_a_flag_replaces_one_of_it():
    plain = PersonalizeConfig()
    assert plain.mode.hardening == PLAIN == Hardening() and _preset(plain) == ("seed", 0, 0)
    hard = PersonalizeConfig.of(harden=True)
    assert hard.mode.hardening == HARDENED and _preset(hard) == ("os", 64, 16)
    mixed = PersonalizeConfig.of(harden=True, code_negatives=16, encoder_init="seed", antipode_codes=0)
    assert _preset(mixed) == ("seed", 16, 0)
    assert PersonalizeConfig.of(code_negatives=None).mode.hardening == PLAIN  # None: the preset's (the CLI's)
    rows = plain.mode.batch_rows(64)
    assert hard.mode.batch_rows(64) == rows + (64 + 16) * plain.mode.samples_per_key
    assert (HARDENED.flags(), PLAIN.flags(), mixed.mode.hardening.flags()) == (
        ["--harden"], [], ["--code-negatives 16"]
    )


def test_settings_are_frozen_and_round_trip_through_the_manifests_flat_dict():
    import dataclasses

    cfg = PersonalizeConfig.of(steps=5, harden=True, code_negatives=8, layers=["0"])
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.train.steps = 6  # type: ignore[misc]
    flat = cfg.to_dict()
    assert flat["harden"] is False and flat["code_negatives"] == 8 and flat["seal"] is False
    assert "payload" not in flat  # an unsealed bundle records no payload setting
    assert PersonalizeConfig.from_dict(flat) == cfg == cfg.replace()
    # null_rows: not the --seal recipe's, left out
    sealed = PersonalizeConfig.of(seal=True, payload="delta", null_rows=3)
    assert isinstance(sealed.mode, SealedConfig) and "null_rows" not in sealed.to_dict()
    assert PersonalizeConfig.from_dict(sealed.to_dict()) == sealed
    assert sealed.replace(steps=9).train.steps == 9


def test_old_manifests_settings_read_with_their_preset_left_none_or_filled():
    """0.1 and 0.2 recorded every field flat, --harden's preset as given (None) or filled."""
    old = {"steps": 7, "harden": True, "encoder_init": None, "code_negatives": None, "antipode_codes": 4,
           "seal": False, "payload": "lora", "payload_rank": 4, "payload_lr": 0.01, "task": None}  # fmt: skip
    cfg = PersonalizeConfig.from_dict(old)
    assert isinstance(cfg.mode, UnsealedConfig) and _preset(cfg) == ("os", 64, 4) and cfg.train.steps == 7
    sealed = PersonalizeConfig.from_dict({**old, "seal": True, "payload": "full"})
    assert sealed.mode == SealedConfig(payload="full")  # its recorded --harden: not part of a sealed config


@pytest.mark.parametrize(
    ("field", "value", "flag"),
    [("encoder_init", "urandom", "--encoder-init"), ("code_negatives", -1, "--code-negatives"),
     ("code_flip_max", 0, "--code-flip-max"), ("code_relax_min", 0.0, "--code-relax-min"),
     ("antipode_codes", -1, "--antipode-codes")],
)  # fmt: skip
def test_bad_hardening_settings_name_their_flag(field, value, flag):
    with pytest.raises(PropError, match=flag):
        PersonalizeConfig.of(**{field: value})


def test_code_negatives_stay_in_the_cube_near_the_user_code():
    rng = np.random.default_rng(0)
    user = torch.where(torch.rand(2, 64) < 0.5, -1.0, 1.0)
    c = code_negatives(user, 40, flip_max=5, relax_min=0.2, rng=rng)
    assert c.shape == (40, 64) and c.abs().max() <= 1
    flipped = c[:10]  # first share: ±1 codes 1..flip_max bits from one of the user codes
    assert set(flipped.unique().tolist()) <= {-1.0, 1.0}
    dist = (flipped[:, None] != user[None]).sum(-1).min(1).values
    assert ((dist >= 1) & (dist <= 5)).all()
    assert not (c[10:, None] == user[None]).all(-1).any()  # the rest moved away from the user codes
    assert code_negatives(user, 0, 5, 0.2, rng).shape == (0, 64)


def _encoder(cfg: PersonalizeConfig) -> torch.Tensor:
    torch.manual_seed(cfg.train.seed)
    with encoder_init(cfg.mode.hardening, cfg.train.seed):
        enc = KeyEncoder(32, [8], [16], 2.0)
    return enc.net[0].weight.detach().clone()


def test_os_init_is_not_the_seeds_and_leaves_the_seeded_stream_alone():
    seeded = PersonalizeConfig.of(seed=5)
    os_init = PersonalizeConfig.of(seed=5, harden=True)
    assert torch.equal(_encoder(seeded), _encoder(seeded))
    a, b = _encoder(os_init), _encoder(os_init)
    assert not torch.equal(a, b) and not torch.equal(a, _encoder(seeded))
    torch.manual_seed(1)
    with encoder_init(os_init.mode.hardening, 5):
        torch.rand(3)
    after = torch.rand(3)
    torch.manual_seed(1)
    assert torch.equal(after, torch.rand(3))


def test_hardened_training_runs_and_keeps_its_settings(tmp_path):
    loaded = load_checkpoint(make_mlp_checkpoint(tmp_path / "m.safetensors"))
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (60, 4)).astype(np.float32)
    user = User(Dataset(x, (-x[:, :2]).astype(np.float32), "d"), rng.integers(0, 2, 32, dtype=np.uint8))
    cfg = PersonalizeConfig.of(steps=5, harden=True, code_negatives=8)
    res = personalize(loaded, [user], cfg)
    assert _preset(cfg)[:2] == ("os", 8)
    assert set(res.final_losses) == {"personal", "fallback", "null"}


def test_far_codes_are_plus_minus_one_codes_40_to_56_of_128_bits_away_from_a_users():
    from prop_cli.train.hardening import far_codes

    rng = np.random.default_rng(0)
    users = torch.from_numpy(rng.integers(0, 2, (2, 128)) * 2.0 - 1).float()
    codes = far_codes(users, 400, rng)
    assert codes.shape == (400, 128) and set(codes.unique().tolist()) == {-1.0, 1.0}
    d = (codes[:, None] != users[None]).sum(-1).min(1).values  # to the nearest user's code
    assert d.min() >= 40 and d.max() <= 56 and len(d.unique()) > 10
    assert far_codes(users, 0, rng).shape == (0, 128)


def test_antipode_codes_are_plus_minus_one_codes_72_to_88_of_128_bits_away_from_a_users():
    from prop_cli.train.hardening import antipode_codes

    rng = np.random.default_rng(0)
    users = torch.from_numpy(rng.integers(0, 2, (1, 128)) * 2.0 - 1).float()
    codes = antipode_codes(users, 400, rng)
    assert codes.shape == (400, 128) and set(codes.unique().tolist()) == {-1.0, 1.0}
    d = (codes != users).sum(-1)
    assert d.min() >= 72 and d.max() <= 88 and len(d.unique()) > 10
    assert antipode_codes(users, 0, rng).shape == (0, 128)


def test_hardened_step_pulls_the_antipode_codes_but_not_the_far_codes(tmp_path, monkeypatch):
    """--harden's step: [K1, K2 | antipode codes, far codes | code-space negatives]; the antipode and far
    codes in one fallback term (not diluted by the 64 code-space negatives). The delta pull takes K1, K2
    and the antipode codes, not the far codes nor the code-space negatives: the codes placed nearer the
    user's than a random key's (objective.delta_pull)."""
    from prop_cli.core.keyed_model import key_codes
    from prop_cli.train import array, objective

    loaded = load_checkpoint(make_mlp_checkpoint(tmp_path / "m.safetensors"))
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (60, 4)).astype(np.float32)
    key = rng.integers(0, 2, 128, dtype=np.uint8)
    user = User(Dataset(x, (-x[:, :2]).astype(np.float32), "d"), key)
    seen: dict = {}
    real_pull, real_loss = objective.delta_pull, array.prop_loss

    def pull(deltas, keys, of=None):
        seen["pulled"], seen["of"] = torch.cat(deltas, 1)[keys].detach(), of
        return real_pull(deltas, keys, of)

    def loss(out, batch, *a, **kw):
        seen["batch"] = batch
        return real_loss(out, batch, *a, **kw)

    monkeypatch.setattr(array, "delta_pull", pull)
    monkeypatch.setattr(array, "prop_loss", loss)
    cfg = PersonalizeConfig.of(steps=1, harden=True, code_negatives=8, far_codes=4, antipode_codes=6)
    res = personalize(loaded, [user], cfg)
    b, s = seen["batch"], cfg.mode.samples_per_key
    assert (b.far_rows, b.code_rows) == ((4 + 6) * s, 8 * s)
    k = cfg.mode.neighbour_keys + cfg.mode.random_keys
    far = b.codes[1 + k : 1 + k + 10]
    d = (far != key_codes(key, cfg.mode.key_encoding)).sum(-1)
    assert ((d[:6] >= 72) & (d[:6] <= 88)).all() and ((d[6:] >= 40) & (d[6:] <= 56)).all()
    with torch.no_grad():  # the pull's rows: the sampled keys and the antipode codes, no more
        want = torch.cat(res.keyed.layer_deltas(b.codes[1 : 1 + k + 6]), 1)
    assert seen["pulled"].shape == want.shape and seen["of"] == k + 10  # the far codes' share dropped
