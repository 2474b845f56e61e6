"""The shared metrics (docs/metrics.md): exact values on hand-made outputs."""

from __future__ import annotations

import pytest
import torch

from prop_cli.core import metrics


def _reg(n=500, d=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    b = torch.randn(n, d, generator=g)
    p = b + torch.randn(n, d, generator=g)
    return b, p


def test_personalization_regression_and_classification():
    b, p = _reg()
    assert metrics.personalization(p, p, b, "regression") == pytest.approx(1.0)
    assert metrics.personalization(b, p, b, "regression") == pytest.approx(0.0)
    assert metrics.personalization((b + p) / 2, p, b, "regression") == pytest.approx(0.75)
    logits = torch.eye(3)[[0, 1, 2, 2]]
    assert metrics.personalization(logits, torch.tensor([0, 1, 2, 0]), logits, "classification") == 0.75


def test_regression_leakage_is_the_fraction_of_the_gap_covered():
    b, p = _reg()
    moves = torch.stack([b, p, b + 0.25 * (p - b), b + 3 * (p - b), b - (p - b)])
    lk = metrics.leakage(moves, p, b, "regression")
    torch.testing.assert_close(lk, torch.tensor([0.0, 1.0, 0.25, 1.0, 0.0]))  # clipped to [0, 1]


def test_regression_leakage_of_noise_around_b_averages_to_zero():
    """Clip the mean, not each sample: outputs scattering around b do not count their positive half."""
    b, p = _reg()
    g = torch.Generator().manual_seed(1)
    noise = b + 0.5 * torch.randn(64, *b.shape, generator=g)
    lk = metrics.leakage(noise, p, b, "regression")
    assert lk.mean() < 0.02 and lk.max() < 0.06
    # Clipping each sample first (the old definition) scored the same noise as clear leakage.
    gap, move = p - b, noise - b
    per_sample = ((move * gap).sum(-1) / (gap**2).sum(-1)).clamp(0, 1).mean(-1)
    assert per_sample.mean() > 0.15


def test_regression_leakage_without_a_gap_is_zero():
    b, _ = _reg()
    assert metrics.leakage(torch.stack([b + 1, b]), b.clone(), b, "regression").tolist() == [0.0, 0.0]


def test_classification_leakage_counts_only_samples_the_user_changed():
    b = torch.eye(3)[[0, 1, 2, 0]]  # the original predicts 0, 1, 2, 0
    p = torch.tensor([0, 2, 2, 1])  # the user differs on samples 1 and 3
    o = torch.stack([torch.eye(3)[[1, 2, 0, 0]], torch.eye(3)[[0, 2, 2, 1]], b])
    torch.testing.assert_close(metrics.leakage(o, p, b, "classification"), torch.tensor([0.5, 1.0, 0.0]))


def test_fidelity_and_summary():
    b, p = _reg(n=10)
    fid = metrics.fidelity(torch.stack([b, b + 1]), b, "regression")
    torch.testing.assert_close(fid, torch.tensor([0.0, 1.0]))
    agree = metrics.fidelity(torch.eye(3)[None, [0, 1, 1]], torch.eye(3)[[0, 1, 2]], "classification")
    torch.testing.assert_close(agree, torch.tensor([2 / 3]))
    s = metrics.summarize(torch.tensor([0.0, 1.0, 2.0]), "max")
    assert s["n"] == 3 and s["mean"] == 1.0 and s["worst"] == 2.0
    assert s["ci95"][0] < 1.0 < s["ci95"][1]
    assert metrics.summarize(torch.tensor([0.5]), "min")["ci95"] == [0.5, 0.5]


def test_bounded_leakage_charges_a_move_larger_than_the_users():
    g = torch.Generator().manual_seed(0)
    b = torch.randn(64, 2, generator=g)
    p = -b  # the user's behaviour: negate
    far = b + 40 * torch.randn(64, 2, generator=g) + 5 * (p - b)  # far away, a little along the gap
    o = torch.stack([p, b + 0.5 * (p - b), b + 3 * (p - b), far])
    raw, bounded = metrics.leakage(o, p, b, "regression"), metrics.bounded_leakage(o, p, b, "regression")
    assert raw.tolist() == pytest.approx([1.0, 0.5, 1.0, 1.0])  # unbounded: a far move saturates
    # The user's behaviour and any move no larger than it score the same; overshooting along the gap
    # is still all of it; the far move scores its cosine with the gap, far below 1.
    assert bounded[:3].tolist() == pytest.approx([1.0, 0.5, 1.0])
    cos = float(((far - b) * (p - b)).sum() / ((far - b).norm() * (p - b).norm()))
    assert bounded[3].item() == pytest.approx(cos) and cos < 0.3
    assert (bounded <= raw + 1e-6).all()


def test_bounded_leakage_for_classification_charges_every_changed_prediction():
    b = torch.nn.functional.one_hot(torch.tensor([0, 0, 1, 1]), 3).float()
    p = torch.tensor([2, 0, 2, 1])  # the user changed samples 0 and 2 only
    exact = torch.nn.functional.one_hot(p, 3).float()
    everything = torch.nn.functional.one_hot(torch.tensor([2, 2, 2, 2]), 3).float()  # changes all four
    o = torch.stack([exact, everything])
    assert metrics.leakage(o, p, b, "classification").tolist() == [1.0, 1.0]
    assert metrics.bounded_leakage(o, p, b, "classification").tolist() == [1.0, 0.5]
