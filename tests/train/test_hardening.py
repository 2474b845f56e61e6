"""Hardened unsealed mode (--harden): its preset, code-space negatives, the unrecorded encoder init."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from prop_adapters import load_checkpoint
from prop_cli.config import PersonalizeConfig
from prop_cli.core.keyed_model import KeyEncoder
from prop_cli.datasources import Dataset
from prop_cli.errors import PropError
from prop_cli.train import User, personalize
from prop_cli.train.hardening import code_negatives, encoder_init
from tests.conftest import make_mlp_checkpoint


def test_preset_fills_only_what_was_not_given():
    plain = PersonalizeConfig().validate()
    assert (plain.encoder_init, plain.code_negatives, plain.antipode_codes) == ("seed", 0, 0)
    hard = PersonalizeConfig(harden=True).validate()
    assert (hard.encoder_init, hard.code_negatives, hard.antipode_codes) == ("os", 64, 16)
    mixed = PersonalizeConfig(harden=True, code_negatives=16, encoder_init="seed", antipode_codes=0)
    mixed.validate()
    assert (mixed.encoder_init, mixed.code_negatives, mixed.antipode_codes) == ("seed", 16, 0)
    assert hard.batch_rows == plain.batch_rows + (64 + 16) * plain.samples_per_key


@pytest.mark.parametrize(
    ("field", "value", "flag"),
    [("encoder_init", "urandom", "--encoder-init"), ("code_negatives", -1, "--code-negatives"),
     ("code_flip_max", 0, "--code-flip-max"), ("code_relax_min", 0.0, "--code-relax-min"),
     ("antipode_codes", -1, "--antipode-codes")],
)  # fmt: skip
def test_bad_hardening_settings_name_their_flag(field, value, flag):
    with pytest.raises(PropError, match=flag):
        PersonalizeConfig(**{field: value}).validate()


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
    torch.manual_seed(cfg.seed)
    with encoder_init(cfg):
        enc = KeyEncoder(32, [8], [16], 2.0)
    return enc.net[0].weight.detach().clone()


def test_os_init_is_not_the_seeds_and_leaves_the_seeded_stream_alone():
    seeded = PersonalizeConfig(seed=5).validate()
    os_init = PersonalizeConfig(seed=5, harden=True).validate()
    assert torch.equal(_encoder(seeded), _encoder(seeded))
    a, b = _encoder(os_init), _encoder(os_init)
    assert not torch.equal(a, b) and not torch.equal(a, _encoder(seeded))
    torch.manual_seed(1)
    with encoder_init(os_init):
        torch.rand(3)
    after = torch.rand(3)
    torch.manual_seed(1)
    assert torch.equal(after, torch.rand(3))


def test_hardened_training_runs_and_keeps_its_settings(tmp_path):
    loaded = load_checkpoint(make_mlp_checkpoint(tmp_path / "m.safetensors"))
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (60, 4)).astype(np.float32)
    user = User(Dataset(x, (-x[:, :2]).astype(np.float32), "d"), rng.integers(0, 2, 32, dtype=np.uint8))
    cfg = PersonalizeConfig(steps=5, harden=True, code_negatives=8)
    res = personalize(loaded, [user], cfg)
    assert (cfg.encoder_init, cfg.code_negatives) == ("os", 8)
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
    cfg = PersonalizeConfig(steps=1, harden=True, code_negatives=8, far_codes=4, antipode_codes=6)
    res = personalize(loaded, [user], cfg)
    b, s = seen["batch"], cfg.samples_per_key
    assert (b.far_rows, b.code_rows) == ((4 + 6) * s, 8 * s)
    k = cfg.neighbour_keys + cfg.random_keys
    far = b.codes[1 + k : 1 + k + 10]
    d = (far != key_codes(key, cfg.key_encoding)).sum(-1)
    assert ((d[:6] >= 72) & (d[:6] <= 88)).all() and ((d[6:] >= 40) & (d[6:] <= 56)).all()
    with torch.no_grad():  # the pull's rows: the sampled keys and the antipode codes, no more
        want = torch.cat(res.keyed.layer_deltas(b.codes[1 : 1 + k + 6]), 1)
    assert seen["pulled"].shape == want.shape and seen["of"] == k + 10  # the far codes' share dropped
