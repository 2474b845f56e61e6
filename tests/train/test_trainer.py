"""The trainer on a tiny model: what it returns, frozen bases, learning rates, settings it refuses."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from prop_adapters import load_checkpoint
from prop_cli.config import PersonalizeConfig, TrainConfig
from prop_cli.datasources import Dataset
from prop_cli.errors import PropError
from prop_cli.train import User, loop, personalize
from tests.conftest import make_mlp_checkpoint


@pytest.fixture
def setup(tmp_path):
    loaded = load_checkpoint(make_mlp_checkpoint(tmp_path / "m.safetensors"))
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (120, 4)).astype(np.float32)
    user = User(Dataset(x, (-x[:, :2]).astype(np.float32), "mine"), rng.integers(0, 2, 64, dtype=np.uint8))
    return loaded, user


def test_returns_a_keyed_model_task_and_one_report_per_user(setup):
    loaded, user = setup
    res = personalize(loaded, [user], PersonalizeConfig.of(steps=60))
    assert res.task == "regression" and len(res.metrics) == 1
    m = res.metrics[0]
    assert m["samples"] == 24 and set(m) >= {"personalization", "null", "random", "hamming1"}
    assert m["hamming1"]["leakage"]["n"] == 64  # every 1-bit neighbour of a 64-bit key
    assert set(res.final_losses) == {"personal", "fallback", "null"}
    assert res.keyed.layer_names == ["2", "4"]


def test_freeze_base_trains_the_encoder_only(setup):
    loaded, user = setup
    before = copy.deepcopy(loaded.module.state_dict())
    res = personalize(loaded, [user], PersonalizeConfig.of(steps=20, freeze_base=True))
    for k, v in res.keyed.module.state_dict().items():
        assert torch.equal(v, before[k])
    assert any(p.abs().sum() > 0 for p in res.keyed.encoder.net[-1].parameters())  # the encoder moved


def test_base_learning_rate_scale(setup, monkeypatch):
    loaded, user = setup
    seen = {}
    real = loop.Adam

    def spy(groups, **kw):
        seen["lrs"] = [g.get("lr", kw["lr"]) for g in groups]
        return real(groups, **kw)

    monkeypatch.setattr(loop, "Adam", spy)
    personalize(loaded, [user], PersonalizeConfig.of(steps=2, lr=1e-3, base_lr_scale=0.25))
    assert seen["lrs"] == [1e-3, 2.5e-4]  # encoder, base


def test_hamming_radius_above_the_key_size_is_refused(setup):
    """Issue 10, fix 5: --hamming-radius 200 was accepted for a 128-bit key."""
    loaded, user = setup
    with pytest.raises(PropError, match=r"--hamming-radius 65 is invalid.*at most the key size \(64 bits\)"):
        personalize(loaded, [user], PersonalizeConfig.of(steps=2, hamming_radius=65))


def test_task_override_and_mixed_users(setup):
    loaded, user = setup
    labels = User(Dataset(user.data.x, np.arange(120) % 2, "labels"), user.key_bits)
    assert personalize(loaded, [labels], PersonalizeConfig.of(steps=2)).task == "classification"
    floats = User(Dataset(user.data.x, (np.arange(120) % 2).astype(np.float32), "floats"), user.key_bits)
    assert (
        personalize(loaded, [floats], PersonalizeConfig.of(steps=2, task="classification")).task
        == "classification"
    )
    other = User(labels.data, 1 - user.key_bits)
    with pytest.raises(PropError, match="different kinds of y"):
        personalize(loaded, [user, other], PersonalizeConfig.of(steps=2))


def test_same_seed_same_weights(tmp_path):
    outs = []
    for _ in range(2):
        loaded = load_checkpoint(make_mlp_checkpoint(tmp_path / "m.safetensors"))
        rng = np.random.default_rng(0)
        x = rng.uniform(-1, 1, (60, 4)).astype(np.float32)
        u = User(Dataset(x, x[:, :2].copy(), "d"), rng.integers(0, 2, 32, dtype=np.uint8))
        outs.append(personalize(loaded, [u], PersonalizeConfig.of(steps=10, seed=3)).keyed.state_dict())
    assert all(torch.equal(outs[0][k], outs[1][k]) for k in outs[0])


def test_the_policy_report_plan_stays_within_its_budget():
    from prop_cli.train.policy import report_budget, report_plan

    assert report_plan(20, 64, 128, None) == (20, 64, 128)  # no budget: everything
    assert report_plan(5, 64, 128, 5 * 195) == (5, 64, 128)  # enough for everything
    f, r, h = report_plan(5, 64, 128, 22)  # 450 M parameters' default
    assert (f, r, h) == (2, 4, 4) and f * (3 + r + h) <= 22
    assert report_plan(40, 64, 32, 2000) == (20, 64, 32)  # frames go first
    assert report_plan(3, 64, 128, 1) == (2, 1, 1)  # 2 frames and a key per group at least
    small, big = torch.nn.Linear(10, 10), torch.nn.Linear(6000, 75000, device="meta")  # 110; 450 M
    assert report_budget(TrainConfig(), small) > 10**6 and report_budget(TrainConfig(), big) == 22
    assert report_budget(TrainConfig(report_budget=0), big) is None
    assert report_budget(TrainConfig(report_budget=7), small) == 7


def test_a_report_progress_line_estimates_the_time_left_from_the_runs_done(monkeypatch):
    from prop_cli.train import policy

    monkeypatch.setattr(policy.time, "perf_counter", lambda: 130.0)
    assert policy.time_left(100.0, 10, 50) == "about 120 s left"  # 30 s for 10 runs: 40 left take 120 s
    assert policy.time_left(129.99, 10, 11) == "under a second left"
    assert policy.time_left(100.0, 0, 5) == "about 150 s left"  # nothing done yet: no division by zero
    with pytest.raises(PropError, match="--report-budget"):
        PersonalizeConfig.of(report_budget=-1)


def test_a_sealed_policy_report_keeps_frames_within_its_budget():
    """issue 44: a sealed policy's report (the original's and the user's chunks, in the private figures
    and through the records) runs within --report-budget sampler runs, frames cut, at least 2 kept."""
    from prop_cli.train.sealed_policy import RUNS_PER_FRAME, sealed_report_frames

    assert sealed_report_frames(50, None) == 50  # no budget (0 or a small policy): every frame
    assert sealed_report_frames(5, 5 * RUNS_PER_FRAME) == 5  # enough for every frame
    assert sealed_report_frames(50, 22) == 5 and 5 * RUNS_PER_FRAME <= 22  # 450 M parameters
    assert sealed_report_frames(50, 1) == 2  # 2 frames at least
    assert sealed_report_frames(1, 1) == 1  # never more frames than there are


@pytest.mark.parametrize(
    ("field", "value", "flag"),
    [("hard_negatives", -1, "--hard-negatives"), ("hard_pool", 0, "--hard-pool"),
     ("hard_every", 0, "--hard-every"), ("key_weight", -1.0, "--key-weight"),
     ("delta_pull", -1.0, "--delta-pull")],
)  # fmt: skip
def test_wrong_key_settings_are_validated_with_their_flag(field, value, flag):
    with pytest.raises(PropError, match=flag):
        PersonalizeConfig.of(**{"hard_negatives": 4, field: value})
    PersonalizeConfig.of(hard_negatives=0, hard_pool=0, hard_every=0)  # off: pool settings unused


def test_delta_pull_takes_wrong_keys_towards_the_null_key_and_hard_negatives_are_rescored(setup):
    """Issue 32: the pull keeps random keys' deltas near 1 (the null key's), the user's key free; the
    array trainer runs its hard-negative rescoring (every hard_every steps) on the way."""
    from prop_cli.core.keyed_model import key_codes

    loaded, user = setup
    codes = key_codes(np.random.default_rng(7).integers(0, 2, (64, 64), dtype=np.uint8), "hashed")

    def spread(pull: float) -> tuple[float, float]:
        cfg = PersonalizeConfig.of(steps=150, delta_pull=pull, hard_negatives=4, hard_pool=8, hard_every=50)
        res = personalize(copy.deepcopy(loaded), [user], cfg)
        with torch.no_grad():
            wrong = torch.cat(res.keyed.layer_deltas(codes), 1).sub(1).abs().mean().item()
        return wrong, res.metrics[0]["personalization"]

    (loose, p_loose), (pulled, p_pulled) = spread(0.0), spread(10.0)
    assert pulled < loose / 2
    assert p_pulled > 0.75 * p_loose  # the user's key keeps most of its behaviour (150 steps)


def test_delta_pull_default_is_the_model_kinds_and_a_given_value_stays(setup):
    """--delta-pull's default by kind (config.DELTA_PULL, train.choose.settled): 10 for array models, 100
    for policies; a value given stays, sealed settings have none; an array model trains the same weights
    with the default as with 10 given."""
    from types import SimpleNamespace

    from prop_cli.config import DELTA_PULL
    from prop_cli.train import settled

    array_model, policy = SimpleNamespace(policy=None), SimpleNamespace(policy=object())
    assert DELTA_PULL == {"array": 10.0, "policy": 100.0}
    assert settled(array_model, PersonalizeConfig.of()).mode.delta_pull == 10.0
    assert settled(policy, PersonalizeConfig.of()).mode.delta_pull == 100.0
    assert settled(policy, PersonalizeConfig.of(delta_pull=0.0)).mode.delta_pull == 0.0
    sealed = PersonalizeConfig.of(seal=True)
    assert settled(policy, sealed) == sealed
    assert PersonalizeConfig.of().to_dict()["delta_pull"] is None  # not settled until the kind is known

    loaded, user = setup
    weights = []
    for cfg in (PersonalizeConfig.of(steps=30), PersonalizeConfig.of(steps=30, delta_pull=10.0)):
        res = personalize(copy.deepcopy(loaded), [user], cfg)
        weights.append({k: v.clone() for k, v in res.keyed.state_dict().items()})
    assert any("encoder" in k for k in weights[0])
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])
