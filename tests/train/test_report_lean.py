"""personalize's report: whether the wrong keys' moves lean systematically to one side of the original
along the user's change (a sign test over keys), and the one warning line it prints then."""

from __future__ import annotations

import pytest
import torch

from prop_cli.cli.personalize_cmd import _warn_lean
from prop_cli.core import metrics
from prop_cli.train.report import key_group


def _outputs(shift: float, keys: int = 16, seed: int = 0):
    """The original b, the user's target p = b + 1, and keys' outputs b + shift (p - b) + noise."""
    g = torch.Generator().manual_seed(seed)
    b = torch.randn(64, 3, generator=g)
    p = b + 1.0
    o = b + shift * (p - b) + 0.05 * torch.randn(keys, 64, 3, generator=g)
    return o, p, b


def test_exact_sign_test_matches_the_binomial():
    assert metrics.sign_test(0, 16) == pytest.approx(2 / 2**16)
    assert metrics.sign_test(14, 2) == pytest.approx(2 * (1 + 16 + 120) / 2**16)
    assert metrics.sign_test(8, 8) == 1.0 and metrics.sign_test(0, 0) == 1.0


def test_every_key_leaning_towards_the_user_is_systematic_and_warned(capsys):
    o, p, b = _outputs(0.02)  # a small drift every key shares
    group = key_group(o, p, b, "regression")
    lean = group["lean"]
    assert (lean["above"], lean["below"]) == (16, 0) and lean["systematic"]
    assert lean["p"] == pytest.approx(2 / 2**16) and lean["mean"] == pytest.approx(0.02, abs=0.005)
    _warn_lean(1, {"random": group, "hamming1": key_group(*_outputs(0.0, seed=1), "regression")})
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("prop: warning: user 1's random keys drift systematically")
    assert "towards your change (16 of 16 keys" in err[0] and "--delta-pull" in err[0]


def test_a_systematic_lean_away_from_the_user_is_reported_not_warned(capsys):
    group = key_group(*_outputs(-0.02), "regression")
    assert group["lean"]["below"] == 16 and group["lean"]["systematic"]
    _warn_lean(1, {"random": group, "hamming1": group})
    assert capsys.readouterr().err == ""


def test_keys_scattering_around_the_original_are_quiet(capsys):
    o, p, b = _outputs(0.0)
    group = key_group(o, p, b, "regression")
    assert group["lean"]["above"] + group["lean"]["below"] == 16 and not group["lean"]["systematic"]
    _warn_lean(1, {"random": group, "hamming1": group})
    assert capsys.readouterr().err == ""


def test_classification_lean_is_the_change_in_the_users_class_probability():
    b = torch.tensor([[2.0, 0.0], [0.0, 2.0]])  # the original predicts 0, then 1
    p = torch.tensor([1, 1])  # the user changes the first sample only
    o = torch.stack([b + torch.tensor([0.0, 1.0]), b - torch.tensor([0.0, 1.0])])
    lean = metrics.lean(o, p, b, "classification")
    assert lean[0] > 0 > lean[1]
    assert key_group(o, p, b, "classification")["lean"]["keys"] == 2
