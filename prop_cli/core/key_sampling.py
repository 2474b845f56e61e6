"""Keys other than the user's, as 0/1 bit arrays: the one place probe and fallback keys are drawn.

Training (K1 neighbours, K2 random keys), the per-user report, the audit's probes and the examples
all draw their keys here, so "a key d bits away" means the same thing everywhere. Keys are uint8
arrays of shape (K, n); nothing here knows about encodings (see ``keyed_model.key_codes``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from itertools import combinations

import numpy as np

# The seed stream of a trainer's hard-negative scoring draws (its inputs), apart from training's.
HARD_STREAM = 0x4A2D_5EED


def _as_keys(keys: np.ndarray) -> np.ndarray:
    return np.atleast_2d(np.asarray(keys, dtype=np.uint8))


def random_keys(n: int, bits: int, rng: np.random.Generator, exclude: np.ndarray | None = None) -> np.ndarray:
    """``n`` uniform random keys; any that equals a key of ``exclude`` (K, bits) gets its first bit flipped.

    A uniform key equals a given one with probability 2^-bits, but "random" means "not the user's".
    """
    keys = rng.integers(0, 2, (n, bits), dtype=np.uint8)
    if exclude is not None:
        for u in _as_keys(exclude):
            keys[(keys == u).all(1), 0] ^= 1
    return keys


def flip_random_bits(keys: np.ndarray, distances: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Row i of ``keys`` with ``distances[i]`` distinct bits flipped, at uniformly random positions."""
    keys = _as_keys(keys).copy()
    ranks = rng.random(keys.shape).argsort(1)
    keys ^= (ranks < np.asarray(distances)[:, None]).astype(np.uint8)
    return keys


def one_bit_neighbours(key: np.ndarray) -> np.ndarray:
    """All ``n`` keys at Hamming distance exactly 1 from ``key`` (n,), bit i flipped in row i."""
    key = np.asarray(key, dtype=np.uint8)
    keys = np.repeat(key[None], len(key), 0)
    keys[np.arange(len(key)), np.arange(len(key))] ^= 1
    return keys


def neighbours_at(key: np.ndarray, d: int, count: int, rng: np.random.Generator) -> np.ndarray:
    """Distinct keys at exactly distance ``d`` from ``key``: all of them when there are <= count."""
    n = len(key)
    if not 1 <= d <= n:
        raise ValueError(f"distance {d} is outside 1..{n}")
    total = math.comb(n, d)
    if total <= count:
        flips = np.zeros((total, n), dtype=bool)
        for row, pos in enumerate(combinations(range(n), d)):
            flips[row, list(pos)] = True
    else:
        flips = np.zeros((0, n), dtype=bool)
        while len(flips) < count:  # top up after dropping the (rare) duplicates
            pos = np.argsort(rng.random((count - len(flips), n)), axis=1)[:, :d]
            new = np.zeros((len(pos), n), dtype=bool)
            np.put_along_axis(new, pos, True, axis=1)
            flips = np.unique(np.concatenate([flips, new]), axis=0)
        flips = flips[rng.permutation(len(flips))[:count]]
    return (np.asarray(key, dtype=bool)[None] ^ flips).astype(np.uint8)


class KeySampler:
    """Eq. 8's K1 (neighbours of the user keys within ``radius``) and K2 (random keys), seeded.

    A quarter of the neighbours are 1-bit neighbours taken in a fixed random cycle, so every one of the
    ``bits`` 1-bit neighbours is seen every few steps instead of by luck; the rest are uniform over
    distance 1..radius.

    Hard negatives (``hard`` > 0; docs/hardening.md, "Wrong keys in closed loop"): every ``every`` steps
    the trainer's ``score`` (the fallback divergence of each key, higher = further from the original)
    rates ``pool`` fresh random keys together with the hard keys kept so far, and the ``hard`` worst are
    kept; half of each step's random keys are then drawn from them, the other half stay uniform. K2 is
    still random keys only (Eq. 8's objective is unchanged): it is sampled where the fallback is worst,
    as K1 samples the boundary around the user's key. Uniform sampling leaves a few keys in a hundred
    whose small action errors compound over an episode.
    """

    def __init__(
        self, user_keys: list[np.ndarray], radius: int, rng: np.random.Generator,
        hard: int = 0, pool: int = 0, every: int = 0,
    ) -> None:  # fmt: skip
        self.users = np.stack(user_keys).astype(np.uint8)
        self.bits = self.users.shape[1]
        self.radius = min(radius, self.bits)
        self.rng = rng
        self._order = rng.permutation(self.bits)
        self._next = 0
        self.hard, self.pool, self.every = hard, pool, every
        self.hard_keys = np.zeros((0, self.bits), np.uint8)
        self._hard_next = 0
        self._steps = 0
        # The pool's own stream: drawing it leaves the training stream (and so a run without hard
        # negatives) as it was.
        self._pool_rng = np.random.default_rng(rng.integers(0, 2**63)) if hard else None

    def neighbours(self, n: int) -> np.ndarray:
        if n == 0:
            return np.zeros((0, self.bits), np.uint8)
        owner = self.rng.integers(0, len(self.users), n)
        keys = self.users[owner].copy()
        n1 = n // 4
        flips = self._order[(self._next + np.arange(n1)) % self.bits]
        self._next += n1
        keys[np.arange(n1), flips] ^= 1
        dist = self.rng.integers(1, self.radius + 1, n - n1)
        keys[n1:] = flip_random_bits(keys[n1:], dist, self.rng)
        return keys

    def random(self, n: int) -> np.ndarray:
        h = min(n // 2, len(self.hard_keys))
        fresh = random_keys(n - h, self.bits, self.rng, exclude=self.users)
        if not h:
            return fresh
        pick = (self._hard_next + np.arange(h)) % len(self.hard_keys)
        self._hard_next += h
        return np.concatenate([fresh, self.hard_keys[pick]])

    def step(self, score: Callable[[np.ndarray], np.ndarray]) -> bool:
        """Call once per training step, before drawing its keys: every ``every`` steps (not the first:
        an untrained encoder answers every key alike) the hard keys are re-chosen with ``score``
        ((K, bits) keys -> (K,) divergences). True when it rescored."""
        self._steps += 1
        if not self.hard or self._steps % self.every:
            return False
        fresh = random_keys(self.pool, self.bits, self._pool_rng, exclude=self.users)
        cand = np.concatenate([self.hard_keys, fresh])
        divergence = np.asarray(score(cand), dtype=np.float64)
        self.hard_keys = cand[np.argsort(-divergence, kind="stable")[: self.hard]]
        self._hard_next = 0
        return True
