"""A vectorised map from non-negative int64 keys to int slots: the voxel grid's key → slot index.

Open addressing with linear probing in two arrays (keys, slots) on pages of their own (`lazy_zeros`): a lookup,
insert or removal of M keys is a few numpy passes over M, not M Python operations. It replaces a ``dict`` of
Python ints, which cost ~120 B a voxel (the entry, its key and slot objects) on the small-object heap and grew in
steps of a new table per resize; here a bucket costs 12 B at a load between ``REBUILD_LOAD`` / 2 and ``MAX_LOAD``
(20–53 B a key), and a grown table's old arrays go back to the kernel whole (docs/BENCHMARKS.md, "The voxel
grid's key index")."""

from __future__ import annotations

import numpy as np

from services.common.own_pages import lazy_zeros

EMPTY = -1  # a bucket never used: a probe stops here
REMOVED = -2  # a bucket whose key was removed: a probe goes on past it, an insert may reuse it
MAX_LOAD = 0.6  # keys and removed buckets together, as a share of the buckets, before the table is rebuilt
REBUILD_LOAD = 0.45  # the most keys a rebuilt table starts with, as a share of its buckets (a power of two)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)  # Fibonacci hashing: the top bits of key × 2^64/φ


class SlotTable:
    """``key -> slot`` for keys ≥ 0 (the voxel grid's packed coordinates) and slots in [0, 2^31)."""

    def __init__(self, capacity: int = 1024) -> None:
        self._live = 0
        self._removed = 0
        self._alloc(max(16, 1 << int(np.ceil(np.log2(max(capacity, 1) / REBUILD_LOAD)))))  # as `_rebuild` sizes

    def _alloc(self, buckets: int) -> None:
        self._bits = buckets.bit_length() - 1
        self._mask = buckets - 1
        self._keys = lazy_zeros((buckets,), np.int64)
        self._keys.fill(EMPTY)
        self._slots = lazy_zeros((buckets,), np.int32)

    def __len__(self) -> int:
        return self._live

    @property
    def buckets(self) -> int:
        return self._keys.shape[0]

    def _home(self, keys: np.ndarray) -> np.ndarray:
        return ((keys.astype(np.uint64) * _GOLDEN) >> np.uint64(64 - self._bits)).astype(np.int64)

    def _positions(self, keys: np.ndarray) -> np.ndarray:
        """The bucket of each key, -1 where the key is absent."""
        pos = self._home(keys)
        out = np.full(keys.shape[0], -1, np.int64)
        todo = np.arange(keys.shape[0])
        while todo.size:
            p = pos[todo]
            found = self._keys[p]
            hit = found == keys[todo]
            out[todo[hit]] = p[hit]
            going_on = ~hit & (found != EMPTY)
            todo = todo[going_on]
            pos[todo] = (p[going_on] + 1) & self._mask
        return out

    def lookup(self, keys: np.ndarray) -> np.ndarray:
        """(M,) int64 slots of ``keys`` ((M,) int64), -1 where a key is absent."""
        keys = np.asarray(keys, np.int64)
        pos = self._positions(keys)
        return np.where(pos >= 0, self._slots[pos].astype(np.int64), -1)

    def insert(self, keys: np.ndarray, slots: np.ndarray) -> None:
        """Add ``keys`` (distinct, ≥ 0, none present) with their ``slots``."""
        keys, slots = np.asarray(keys, np.int64), np.asarray(slots, np.int64)
        if keys.shape != slots.shape or keys.ndim != 1:
            raise ValueError("keys and slots must be (M,) arrays of one length")
        if keys.size and keys.min() < 0:
            raise ValueError("SlotTable keys must be >= 0")
        if self._live + self._removed + keys.size > MAX_LOAD * self.buckets:
            self._rebuild(self._live + keys.size)
        pos = self._home(keys)
        todo = np.arange(keys.size)
        while todo.size:  # each round, every open bucket wanted goes to the first key that wants it
            p = pos[todo]
            open_ = self._keys[p] < 0  # EMPTY or REMOVED
            wanted, first = np.unique(p[open_], return_index=True)
            won = todo[open_][first]
            self._removed -= int(np.count_nonzero(self._keys[wanted] == REMOVED))
            self._keys[wanted] = keys[won]
            self._slots[wanted] = slots[won]
            lost = np.ones(todo.size, bool)
            lost[np.flatnonzero(open_)[first]] = False
            todo = todo[lost]
            pos[todo] = (pos[todo] + 1) & self._mask
        self._live += keys.size

    def remove(self, keys: np.ndarray) -> None:
        """Remove ``keys`` (each present)."""
        pos = self._present(keys)
        self._keys[pos] = REMOVED
        self._live -= pos.size
        self._removed += pos.size

    def assign(self, keys: np.ndarray, slots: np.ndarray) -> None:
        """Give ``keys`` (each present) new ``slots``."""
        self._slots[self._present(keys)] = np.asarray(slots, np.int64)

    def _present(self, keys: np.ndarray) -> np.ndarray:
        pos = self._positions(np.asarray(keys, np.int64))
        if (pos < 0).any():
            raise KeyError(f"{int(np.count_nonzero(pos < 0))} keys are not in the table")
        return pos

    def items(self) -> tuple[np.ndarray, np.ndarray]:
        """Every (key, slot), as two (len,) int64 arrays in bucket order."""
        used = self._keys >= 0
        return self._keys[used].copy(), self._slots[used].astype(np.int64)

    def _rebuild(self, live: int) -> None:
        """Re-insert every key into buckets for ``live`` keys at no more than REBUILD_LOAD (removed buckets
        dropped)."""
        keys, slots = self.items()
        buckets = self.buckets
        while live > REBUILD_LOAD * buckets:
            buckets *= 2
        self._live = self._removed = 0
        self._keys = self._slots = None  # freed before their successors are written
        self._alloc(buckets)
        self.insert(keys, slots)
