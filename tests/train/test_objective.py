"""The Eq. 8 objective: each loss term, and the row order a step's batch is built in."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from prop_cli.config import UnsealedConfig
from prop_cli.core.key_sampling import KeySampler
from prop_cli.core.keyed_model import key_codes
from prop_cli.errors import PropError
from prop_cli.train.array import FallbackPool, UserPool, make_batch
from prop_cli.train.objective import Batch, check_user_keys, delta_pull, prop_loss, row_loss


def test_row_loss_per_term():
    out, target = torch.tensor([[1.0, 2.0], [0.0, 0.0]]), torch.tensor([[1.0, 0.0], [1.0, 1.0]])
    torch.testing.assert_close(row_loss(out, target, "regression", distill=False), torch.tensor([2.0, 1.0]))
    logits, labels = torch.tensor([[2.0, 0.0], [0.0, 1.0]]), torch.tensor([0, 0])
    torch.testing.assert_close(
        row_loss(logits, labels, "classification", distill=False),
        F.cross_entropy(logits, labels, reduction="none"),
    )
    kl = row_loss(logits, logits, "classification", distill=True)  # KL to its own softmax: zero
    torch.testing.assert_close(kl, torch.zeros(2))
    teacher = torch.tensor([[0.0, 3.0], [0.0, 1.0]])
    p = F.softmax(teacher, -1)
    want = (p * (p.log() - F.log_softmax(logits, -1))).sum(-1)
    torch.testing.assert_close(row_loss(logits, teacher, "classification", distill=True), want)


def _batch(user=2, keyed=3, null=2, d=1) -> tuple[Batch, torch.Tensor]:
    rows = user + keyed + null
    out = torch.arange(rows, dtype=torch.float32)[:, None].repeat(1, d)
    batch = Batch(
        x=torch.zeros(rows, 1), sample_index=torch.arange(rows), key_index=torch.arange(rows),
        codes=torch.zeros(1, 8), user_rows=user, null_rows=null,
        user_targets=torch.zeros(user, d), fallback_targets=torch.zeros(keyed + null, d),
    )  # fmt: skip
    return batch, out


def test_prop_loss_reads_rows_as_user_then_keyed_then_null():
    batch, out = _batch()  # outputs 0..6; every target 0: each row's loss is its index squared
    total, parts = prop_loss(out, batch, "regression", null_weight=10.0)
    assert parts["personal"] == pytest.approx((0 + 1) / 2)  # rows 0, 1
    assert parts["fallback"] == pytest.approx((4 + 9 + 16) / 3)  # rows 2, 3, 4
    assert parts["null"] == pytest.approx((25 + 36) / 2)  # rows 5, 6
    assert total.item() == pytest.approx(parts["personal"] + parts["fallback"] + 10 * parts["null"])


def test_code_space_negatives_add_a_term_of_their_own_instead_of_diluting_k1_k2():
    batch, out = _batch(keyed=5)  # rows 2..6 sampled: 2, 3, 4 K1/K2 keys, 5, 6 code-space negatives
    batch.code_rows = 2
    _, parts = prop_loss(out, batch, "regression", null_weight=1.0)
    assert parts["fallback"] == pytest.approx((4 + 9 + 16) / 3 + (25 + 36) / 2)
    assert parts["null"] == pytest.approx((49 + 64) / 2)


def test_far_codes_and_code_space_negatives_are_a_term_each():
    batch, out = _batch(keyed=6)  # sampled rows: 2, 3 K1/K2; 4, 5 far (and antipode) codes; 6, 7 code-space
    batch.far_rows, batch.code_rows = 2, 2
    _, parts = prop_loss(out, batch, "regression", null_weight=1.0)
    assert parts["fallback"] == pytest.approx((4 + 9) / 2 + (16 + 25) / 2 + (36 + 49) / 2)


def test_key_weight_scales_the_sampled_keys_term_only():
    batch, out = _batch()
    total, parts = prop_loss(out, batch, "regression", null_weight=10.0, key_weight=4.0)
    assert total.item() == pytest.approx(parts["personal"] + 4 * parts["fallback"] + 10 * parts["null"])
    assert parts["fallback"] == pytest.approx((4 + 9 + 16) / 3)  # the progress line: unweighted


def test_delta_pull_is_the_mean_square_of_the_sampled_keys_deltas_from_one_over_all_layers():
    user = [torch.full((1, 2), 3.0), torch.full((1, 3), 3.0)]  # the user's deltas: free, not pulled
    sampled = [torch.tensor([[1.0, 2.0], [1.0, 1.0]]), torch.tensor([[0.0, 1.0, 1.0], [1.0, 1.0, 3.0]])]
    null = [torch.ones(1, 2), torch.ones(1, 3)]
    deltas = [torch.cat(parts) for parts in zip(user, sampled, null)]
    assert delta_pull(deltas, slice(1, 3)).item() == pytest.approx((1 + 1 + 4) / 10)
    assert delta_pull(deltas, slice(1, 1)).item() == 0.0  # no key sampled
    # of=4: the two pulled rows keep the weight they have among 4 (two more, the far codes, unpulled)
    assert delta_pull(deltas, slice(1, 3), of=4).item() == pytest.approx((1 + 1 + 4) / 20)


def test_prop_loss_without_sampled_keys_has_no_keyed_term():
    batch, out = _batch(keyed=0)
    _, parts = prop_loss(out, batch, "regression", null_weight=1.0)
    assert parts["fallback"] == 0.0 and parts["null"] == pytest.approx((4 + 9) / 2)


def test_make_batch_layout_and_targets():
    cfg = UnsealedConfig(null_rows=3, random_keys=2, neighbour_keys=4, samples_per_key=2, fallback_noise=0.0)
    rng = np.random.default_rng(0)
    key = rng.integers(0, 2, 16, dtype=np.uint8)
    ux, uy = torch.randn(10, 2), torch.randn(10, 1)
    original = torch.nn.Linear(2, 1)
    pool = FallbackPool(torch.randn(20, 2), original, noise=0.0, sigma=0.5)
    users = UserPool([ux], [uy])
    b = make_batch(cfg, 4, rng, KeySampler([key], 8, rng), key_codes(key, "hashed"), users, pool)
    k = cfg.random_keys + cfg.neighbour_keys
    assert b.user_rows == 4 and b.null_rows == 3
    assert b.x.shape == (4 + 3, 2)  # distinct samples: user rows, then the null rows' fallback samples
    assert len(b.key_index) == 4 + k * 2 + 3 and b.codes.shape == (1 + k, 16)
    assert (b.key_index[:4] == 0).all()  # the user's code
    assert b.key_index[4:-3].tolist() == [1 + i for i in range(k) for _ in range(2)]  # each sampled key x2
    assert (b.key_index[-3:] == 1 + k).all()  # the row after the codes: the null key
    assert (b.sample_index[-3:] == torch.arange(4, 7)).all()
    with torch.no_grad():  # fallback targets are the original's outputs on each row's sample
        torch.testing.assert_close(b.fallback_targets, original(b.x[b.sample_index[4:]]))
    assert torch.equal(b.codes[0], key_codes(key, "hashed")[0])
    assert b.code_rows == 0
    near = torch.zeros(3, 16)  # --harden's code-space negatives: after the sampled keys, 2 rows each
    users = UserPool([ux], [uy])
    hb = make_batch(cfg, 4, rng, KeySampler([key], 8, rng), key_codes(key, "hashed"), users, pool, near)
    assert (hb.code_rows, hb.far_rows) == (6, 0)
    sampler = KeySampler([key], 8, rng)
    fb = make_batch(cfg, 4, rng, sampler, key_codes(key, "hashed"), users, pool, near, far=1)
    assert (fb.code_rows, fb.far_rows) == (4, 2)  # the first extra code is a far code, the rest code-space


def test_fallback_pool_perturbs_a_share_and_labels_it_with_the_original():
    original = torch.nn.Linear(3, 2)
    x = torch.randn(50, 3)
    pool = FallbackPool(x, original, noise=0.5, sigma=0.5)
    xs, ts = pool.draw(8, np.random.default_rng(0))
    given = [(xs[i] == x).all(1).any().item() for i in range(8)]
    assert given == [True] * 4 + [False] * 4  # the last half is new inputs around the given ones
    with torch.no_grad():
        torch.testing.assert_close(ts, original(xs))
    xs0, _ = FallbackPool(x, original, noise=0.0, sigma=0.5).draw(8, np.random.default_rng(0))
    assert all((xs0[i] == x).all(1).any() for i in range(8))


def test_users_with_close_keys_are_refused():
    a = np.zeros(32, np.uint8)
    b = a.copy()
    b[:5] = 1
    check_user_keys([a, b], radius=2)  # 5 bits apart, radius 2: K1 sets do not overlap
    with pytest.raises(PropError, match="5 bits apart"):
        check_user_keys([a, b], radius=3)


def test_prop_loss_on_every_row_at_once_is_the_per_term_loss_bit_for_bit():
    """Regression: one squared error over all rows (fewer small operators a step), sliced into Eq. 8's
    terms, gives each term and the gradient exactly as a row_loss per term does; float64 user targets
    (not the fallback's dtype) take the per-term path."""
    torch.manual_seed(0)
    batch, _ = _batch(user=5, keyed=9, null=4, d=3)
    batch.far_rows = 3
    batch.user_targets, batch.fallback_targets = torch.randn(5, 3), torch.randn(13, 3)
    out = torch.randn(18, 3, requires_grad=True)

    def by_term(out: torch.Tensor) -> torch.Tensor:
        personal = row_loss(out[:5], batch.user_targets, "regression", distill=False).mean()
        fb = row_loss(out[5:], batch.fallback_targets, "regression", distill=False)
        keyed = fb[:6].mean() + fb[6:9].mean()
        return personal + keyed + 10.0 * fb[-4:].mean()

    total, parts = prop_loss(out, batch, "regression", null_weight=10.0)
    (grad,) = torch.autograd.grad(total, out)
    want = by_term(out)
    (want_grad,) = torch.autograd.grad(want, out)
    assert torch.equal(total, want) and torch.equal(grad, want_grad)
    assert parts["null"] == row_loss(out[-4:], batch.fallback_targets[-4:], "regression", False).mean().item()
    batch.user_targets = batch.user_targets.double()
    total64, _ = prop_loss(out, batch, "regression", null_weight=10.0)
    assert torch.equal(total64, by_term(out))


def test_an_all_noisy_fallback_draw_takes_no_given_rows_and_leaves_the_stream_as_drawing_none_did():
    x = torch.randn(40, 3)
    original = torch.nn.Linear(3, 2)
    rng, twin = np.random.default_rng(5), np.random.default_rng(5)
    xs, ts = FallbackPool(x, original, noise=1.0, sigma=0.5).draw(8, rng)
    assert not any((xs[i] == x).all(1).any() for i in range(8))
    twin.integers(0, len(x), 0)  # what the draw did before: no given rows, drawn all the same
    bank = FallbackPool(x, original, noise=1.0, sigma=0.5)._noisy(8, twin)
    assert torch.equal(xs, bank[0]) and torch.equal(ts, bank[1])
    assert rng.integers(0, 2**62) == twin.integers(0, 2**62)


def test_delta_pull_on_joined_deltas_is_the_per_layer_pull_bit_for_bit():
    from prop_cli.core.keyed_model import JoinedDeltas

    torch.manual_seed(1)
    joined = (1 + torch.randn(7, 5)).requires_grad_()
    split = JoinedDeltas(joined, [2, 3])
    as_list = [d.clone() for d in split]
    for keys, of in ((slice(1, 4), 6), (slice(2, 2), None)):
        got, want = delta_pull(split, keys, of), delta_pull(as_list, keys, of)
        assert torch.equal(got, want)
    (grad,) = torch.autograd.grad(delta_pull(split, slice(1, 4), 6), joined)
    (want_grad,) = torch.autograd.grad(delta_pull(list(split), slice(1, 4), 6), joined)
    assert torch.equal(grad, want_grad) and grad[1:4].abs().sum() > 0 and grad[4:].abs().sum() == 0
