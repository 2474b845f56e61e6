"""Decrypted behaviours kept between connections: an LRU cache with a memory cap (``--cache-mb``).

A connection whose key is in the cache is not decrypted (nor checked) again: the key was checked when it
entered, against the bundle this server loaded. Entries are found by an HMAC-SHA256 of the key bits under
a secret drawn when the server starts (never the key itself, never written anywhere, gone with the
process). A behaviour larger than the whole cap is not kept. A connection holds its own reference, so an
entry evicted while in use stays alive for that connection (the cap bounds what the cache keeps for the
connections to come).
"""

from __future__ import annotations

import hashlib
import hmac
import os
import threading
from collections import OrderedDict

import numpy as np
import torch

from .rows import Behaviour, Deltas, Folded


def behaviour_bytes(behaviour: Behaviour) -> int:
    """Memory a behaviour holds (its tensors; a Folded module's parameters that are its own copies)."""
    if behaviour is None:
        return 0
    if isinstance(behaviour, Deltas):
        tensors = behaviour.deltas
    elif isinstance(behaviour, Folded):
        tensors = list(behaviour.module.parameters())
    else:
        tensors = list(behaviour.tensors().values())
    return sum(t.numel() * t.element_size() for t in tensors if isinstance(t, torch.Tensor))


class BehaviourCache:
    """``get(key) -> (hit, behaviour)``, ``put(key, behaviour)``; at most ``cap_bytes`` kept."""

    def __init__(self, cap_bytes: int) -> None:
        self.cap = int(cap_bytes)
        self._secret = os.urandom(32)
        self._items: OrderedDict[bytes, tuple[Behaviour, int]] = OrderedDict()
        self._lock = threading.Lock()
        self.bytes = 0
        self.hits = self.misses = self.evictions = 0

    def _id(self, key: np.ndarray) -> bytes:
        return hmac.new(self._secret, np.ascontiguousarray(key).tobytes(), hashlib.sha256).digest()

    def __len__(self) -> int:
        return len(self._items)

    def get(self, key: np.ndarray) -> tuple[bool, Behaviour]:
        ident = self._id(key)
        with self._lock:
            item = self._items.get(ident)
            if item is None:
                self.misses += 1
                return False, None
            self._items.move_to_end(ident)
            self.hits += 1
            return True, item[0]

    def put(self, key: np.ndarray, behaviour: Behaviour) -> None:
        size = behaviour_bytes(behaviour)
        if size > self.cap:
            return
        ident = self._id(key)
        with self._lock:
            old = self._items.pop(ident, None)
            if old is not None:
                self.bytes -= old[1]
            self._items[ident] = (behaviour, size)
            self.bytes += size
            while self.bytes > self.cap:
                _, (_, gone) = self._items.popitem(last=False)
                self.bytes -= gone
                self.evictions += 1
