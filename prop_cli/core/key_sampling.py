"""Keys other than the user's, as 0/1 bit arrays: the one place probe and fallback keys are drawn.

Training (K1 neighbours, K2 random keys), the per-user report, the audit's probes and the examples
all draw their keys here, so "a key d bits away" means the same thing everywhere. Keys are uint8
arrays of shape (K, n); nothing here knows about encodings (see ``keyed_model.key_codes``).
"""

from __future__ import annotations

import math
from itertools import combinations

import numpy as np


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
    """

    def __init__(self, user_keys: list[np.ndarray], radius: int, rng: np.random.Generator) -> None:
        self.users = np.stack(user_keys).astype(np.uint8)
        self.bits = self.users.shape[1]
        self.radius = min(radius, self.bits)
        self.rng = rng
        self._order = rng.permutation(self.bits)
        self._next = 0

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
        return random_keys(n, self.bits, self.rng, exclude=self.users)
