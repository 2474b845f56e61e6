"""Probe and fallback keys: one module draws them for training, the report, the audit and examples."""

from __future__ import annotations

import math

import numpy as np
import pytest

from prop_cli.core.key_sampling import (
    KeySampler,
    flip_random_bits,
    neighbours_at,
    one_bit_neighbours,
    random_keys,
)


def test_neighbours_at_exact_distance_distinct_and_exhaustive():
    rng = np.random.default_rng(1)
    user = rng.integers(0, 2, 64).astype(np.uint8)
    ones = neighbours_at(user, 1, 256, rng)
    assert len(ones) == 64  # the whole 1-bit neighbourhood, each once
    assert len(np.unique(ones, axis=0)) == 64
    for d in (2, 5):
        keys = neighbours_at(user, d, 100, rng)
        assert len(keys) == 100 and len(np.unique(keys, axis=0)) == 100
        assert set((keys != user).sum(1)) == {d}
    assert len(neighbours_at(user[:32], 2, 10_000, rng)) == math.comb(32, 2)
    with pytest.raises(ValueError):
        neighbours_at(user, 65, 1, rng)


def test_one_bit_neighbours_and_flips():
    key = np.array([1, 0, 1, 1], np.uint8)
    ones = one_bit_neighbours(key)
    assert ones.shape == (4, 4) and ((ones != key).sum(1) == 1).all() and (np.diag(ones) != key).all()
    flipped = flip_random_bits(np.repeat(key[None], 3, 0), np.array([0, 2, 4]), np.random.default_rng(0))
    assert (flipped != key).sum(1).tolist() == [0, 2, 4]


def test_random_keys_never_equal_an_excluded_key():
    rng = np.random.default_rng(0)
    user = np.zeros(8, np.uint8)  # a 1-in-256 key: 4096 draws hit it ~16 times
    keys = random_keys(4096, 8, rng, exclude=user)
    assert keys.shape == (4096, 8) and not (keys == user).all(1).any()


def test_sampler_cycles_through_every_one_bit_neighbour_and_stays_within_radius():
    user = np.random.default_rng(2).integers(0, 2, 32).astype(np.uint8)
    s = KeySampler([user], radius=3, rng=np.random.default_rng(0))
    seen = set()
    for _ in range(4):  # 4 draws of 32: 8 one-bit neighbours each, 32 in all
        keys = s.neighbours(32)
        d = (keys != user).sum(1)
        assert 1 <= d.min() and d.max() <= 3
        seen |= {int(np.flatnonzero(k != user)[0]) for k in keys[:8]}
    assert seen == set(range(32))
    assert not (s.random(512) == user).all(1).any()


def test_sampler_hard_negatives_keep_the_worst_scored_keys_and_draw_half_of_k2_from_them():
    user = np.random.default_rng(3).integers(0, 2, 32).astype(np.uint8)
    s = KeySampler([user], radius=3, rng=np.random.default_rng(0), hard=4, pool=64, every=10)
    scored: list[np.ndarray] = []

    def score(keys: np.ndarray) -> np.ndarray:  # "divergence": the number of ones in the key's first byte
        scored.append(keys)
        return keys[:, :8].sum(1).astype(float)

    assert not any(s.step(score) for _ in range(9)) and len(s.random(8)) == 8  # nothing kept yet: all fresh
    assert s.step(score)  # the 10th step rescores
    assert len(scored[0]) == 64 and len(s.hard_keys) == 4
    assert s.hard_keys[:, :8].sum(1).min() >= np.sort(scored[0][:, :8].sum(1))[-4]  # the 4 worst
    keys = s.random(8)
    assert len(keys) == 8 and not (keys == user).all(1).any()
    hard = {k.tobytes() for k in s.hard_keys}
    assert sum(k.tobytes() in hard for k in keys[4:]) == 4  # half of K2 from the kept keys
    for _ in range(10):
        s.step(score)
    assert len(scored[1]) == 64 + 4  # the kept keys compete with a fresh pool


def test_sampler_without_hard_negatives_draws_what_it_drew_before():
    user = np.random.default_rng(3).integers(0, 2, 32).astype(np.uint8)
    a = KeySampler([user], radius=3, rng=np.random.default_rng(5))
    b = KeySampler([user], radius=3, rng=np.random.default_rng(5), hard=0, pool=256, every=200)
    for _ in range(3):
        assert not b.step(lambda k: np.zeros(len(k)))
        assert (a.neighbours(8) == b.neighbours(8)).all()
        assert (a.random(8) == b.random(8)).all()
