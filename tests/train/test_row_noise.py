"""Per-row random draws (prop_cli.train.row_noise): a row's draws do not depend on the rows beside it."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from prop_cli.errors import PropError
from prop_cli.train.row_noise import RowNoise

RANDN, DROPOUT = torch.randn, F.dropout


class Noisy(nn.Module):
    """What LeRobot's policies draw in training: dropout (batch-first and sequence-first), attention
    dropout, Gaussian noise like a tensor, a normal of a given size, a Beta time (a Dirichlet draw from
    per-row parameters), an integer timestep, and one draw for the whole batch (a crop's offset)."""

    def __init__(self) -> None:
        super().__init__()
        self.lin = nn.Linear(6, 8)
        self.drop = nn.Dropout(0.3)
        self.attn = nn.MultiheadAttention(8, 2, dropout=0.3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b = len(x)
        h = self.drop(self.lin(x))  # (B, 8)
        seq = h[None].expand(3, b, 8)  # (S, B, D), as ACT's transformer takes it
        a = self.attn(seq, seq, seq)[0].mean(0)
        eps = torch.randn_like(a)
        noise = torch.normal(0.0, 1.0, size=(b, 4))
        t = torch.distributions.Beta(torch.tensor(1.5), torch.tensor(1.0)).sample((b,))
        step = torch.randint(0, 100, (b,))
        shift = torch.randint(0, 5, (1,))  # drawn once, whatever the batch
        return torch.cat([a + eps, noise, t[:, None], step[:, None].float(), shift.expand(b, 1).float()], 1)


@pytest.fixture
def noisy():
    torch.manual_seed(0)
    return Noisy().train()


def probe(model, x):
    return RowNoise.probe(lambda rows, _: model(x[:rows]), (7,), model)


class Direct(nn.Module):
    """Draws with an operator called directly, outside the random functions prop wraps."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        eps = torch.ops.aten.randn.default([len(x), x.shape[1]])
        return x + eps + torch.randn_like(x)


@pytest.mark.parametrize("make", [Noisy, Direct])
def test_a_rows_draws_are_the_same_whatever_rows_share_its_forward(make):
    torch.manual_seed(0)
    noisy = make().train()
    x = torch.randn(7, 6)
    noise, why = probe(noisy, x)
    assert why is None and noise is not None
    # Draws made by torch's random functions need the dispatch mode only inside them; others, throughout.
    assert noise.covered == (make is Noisy)
    with noise.rows(3, torch.arange(7), 7):
        whole = noisy(x)
    for ids in (torch.arange(0, 4), torch.arange(4, 7), torch.tensor([1, 5, 6])):
        with noise.rows(3, ids, 7):
            part = noisy(x[ids])
        assert torch.allclose(part, whole[ids], atol=1e-6)
    with noise.rows(4, torch.arange(7), 7):  # another step draws again
        assert not torch.allclose(noisy(x)[:, :8], whole[:, :8])
    # torch's own functions are back: nothing outside a step draws per row.
    assert torch.randn is RANDN and "normal_" not in torch.Tensor.__dict__ and F.dropout is DROPOUT


def test_one_process_is_the_forward_it_replaces_in_distribution(noisy):
    x = torch.randn(4000, 6)
    noise, _ = probe(noisy, x)
    with noise.rows(0, torch.arange(len(x)), len(x)):
        out = noisy(x)
    noise_cols, t, step = out[:, 8:12], out[:, 12], out[:, 13]
    assert abs(noise_cols.mean()) < 0.05 and abs(noise_cols.std() - 1) < 0.05
    assert abs(t.mean() - 0.6) < 0.02  # Beta(1.5, 1) has mean 0.6
    assert step.min() >= 0 and step.max() <= 99 and len(step.unique()) == 100
    with noise.rows(0, torch.arange(len(x)), len(x)):
        h = noisy.drop(torch.ones(len(x), 8))
    assert abs((h == 0).float().mean() - 0.3) < 0.02  # dropout keeps its rate and scale
    assert torch.allclose(h[h != 0], torch.full_like(h[h != 0], 1 / 0.7))


def test_a_forward_that_draws_nothing_needs_no_noise():
    model = nn.Sequential(nn.Linear(3, 4), nn.Dropout(0.0)).train()
    assert probe(model, torch.randn(5, 3)) == (None, None)
    assert probe(model.eval(), torch.randn(5, 3)) == (None, None)


def test_draws_that_change_with_the_rows_are_reported_not_guessed():
    class Sometimes(nn.Module):
        def forward(self, x):
            return x + (torch.randn_like(x) if len(x) % 2 else 0)

    noise, why = probe(Sometimes(), torch.randn(5, 3))
    assert noise is None and "change with the number of rows" in why


def test_a_forward_drawing_otherwise_than_probed_stops_with_one_line(noisy):
    x = torch.randn(5, 6)
    noise, _ = probe(noisy, x)
    noisy.eval()  # no dropout now: the draws are not the probed ones
    with pytest.raises(PropError, match="differ from those probed"), noise.rows(0, torch.arange(5), 5):
        noisy(x)
