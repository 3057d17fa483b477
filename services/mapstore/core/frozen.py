"""Frozen sums: the summed contributions of folded keyframes, one `FrozenSums` per PCA version (core/folding.py).

Nothing but a PCA refit, the compaction of an old version or a rebuild reads them again, so their merged rows
live in a `SumsStore` the caller gives. `MemorySums` (the default) holds them as arrays;
``services/mapstore/frozen_files.py`` keeps them in files beside the map's database, out of the process's memory:
on a 10,000-frame stream they were the mapstore's largest growing part (26k → 122k rows, docs/BENCHMARKS.md).
Every read and every merge handles `chunk_rows` (4,096) rows at a time, so with files neither ever holds a
version's whole sums (an in-memory merge held ~4 copies of them).
"""
from __future__ import annotations

import dataclasses
from typing import Iterable, Iterator, Protocol

import numpy as np

from services.mapstore.core.fusion import Contribution, merge_contributions

# rows of stored sums read and merged at once: a merge holds ~2.5x a chunk's sums beside the rows pending. At
# 16,384 a merge into the 10,000-frame stream's ~55k stored rows peaked at 18 MB, which set the mapstore's
# high-water once folding began; at 4,096, 7.6 MB (docs/BENCHMARKS.md, forty-eighth session)
CHUNK_ROWS = 4096


class SumsStore(Protocol):
    """Where merged frozen rows are kept: each `write` makes a run of rows (ascending distinct keys) that is read
    back by row range until it is discarded."""

    def write(self, chunks: Iterable[Contribution]) -> object:
        """Store the rows of ``chunks`` in order as one run; returns its handle."""

    def rows(self, handle: object) -> int:
        """Rows in a run."""

    def read(self, handle: object, start: int, stop: int) -> Contribution:
        """Rows ``start:stop`` of a run."""

    def discard(self, handle: object) -> None:
        """Forget a run."""


class MemorySums:
    """A `SumsStore` in memory: a run is one contribution (its chunks joined)."""

    def write(self, chunks: Iterable[Contribution]) -> Contribution:
        return merge_contributions(list(chunks))  # chunks have ascending distinct keys: joined, nothing summed

    def rows(self, handle: Contribution) -> int:
        return handle.keys.size

    def read(self, handle: Contribution, start: int, stop: int) -> Contribution:
        return rows_of(handle, start, stop)

    def discard(self, handle: Contribution) -> None:
        pass


def rows_of(c: Contribution, start: int, stop: int) -> Contribution:
    """Rows ``start:stop`` of a contribution (views)."""
    return Contribution(*(None if a is None else a[start:stop]
                          for a in (getattr(c, f.name) for f in dataclasses.fields(Contribution))))


class FrozenSums:
    """The summed contributions of the folded keyframes of one PCA version (or of those without codes).

    Added contributions wait in memory and are merged into the stored run (sort by key, sum) once they hold as
    many voxels as a quarter of it (at least ``min_pending``): each voxel is re-sorted O(log) times over a stream,
    and the rows in memory stay within a quarter of the run. Iterating gives everything added as contributions of
    at most ``chunk_rows`` rows, in ascending distinct keys.
    """

    chunk_rows: int = CHUNK_ROWS

    def __init__(self, store: SumsStore | None = None, min_pending: int = 4096, chunk_rows: int | None = None) -> None:
        self._store = store if store is not None else MemorySums()
        self._run: object | None = None
        self._run_rows = 0
        self._pending: list[Contribution] = []
        self._pending_rows = 0
        self.min_pending = min_pending
        if chunk_rows is not None:
            self.chunk_rows = chunk_rows
        self.with_codes: bool | None = None  # whether the rows carry code sums (None until the first add)

    def add(self, c: Contribution) -> None:
        """Add one keyframe's contribution (its sums in this part's version)."""
        if self.with_codes is None:
            self.with_codes = c.codes is not None
        elif self.with_codes != (c.codes is not None):
            raise ValueError("cannot add contributions with and without codes to the same sums")
        self._pending.append(c)
        self._pending_rows += c.keys.size
        if self._pending_rows >= max(self.min_pending, self._run_rows // 4):
            self._merge()

    def _merge(self) -> None:
        if not self._pending:
            return
        new, old = merge_contributions(self._pending), self._run
        self._run = self._store.write([new] if old is None else self._merged_with(old, new))  # may raise (disk
        # full): the pending rows and the old run are then kept
        self._run_rows = self._store.rows(self._run)
        self._pending, self._pending_rows = [], 0
        if old is not None:
            self._store.discard(old)

    def _merged_with(self, old: object, new: Contribution) -> Iterator[Contribution]:
        """The stored run ``old`` and ``new`` (ascending distinct keys) summed, a chunk of the run at a time with
        the rows of ``new`` whose keys fall in its range."""
        total, taken = self._store.rows(old), 0
        for start in range(0, total, self.chunk_rows):
            part = self._store.read(old, start, min(start + self.chunk_rows, total))
            end = (int(np.searchsorted(new.keys, part.keys[-1], side="right"))
                   if start + self.chunk_rows < total else new.keys.size)
            yield merge_contributions([part, rows_of(new, taken, end)])
            taken = end
        if total == 0:
            yield new

    def __iter__(self) -> Iterator[Contribution]:
        """Everything added, in chunks of at most ``chunk_rows`` rows with ascending distinct keys."""
        self._merge()
        for start in range(0, self._run_rows, self.chunk_rows):
            yield self._store.read(self._run, start, min(start + self.chunk_rows, self._run_rows))

    def contribution(self) -> Contribution:
        """Everything added, as one contribution (distinct keys; in memory: for tests and small maps)."""
        chunks = list(self)
        if not chunks:
            raise ValueError("nothing folded into these sums yet")
        return merge_contributions(chunks)

    def discard(self) -> None:
        """Forget everything (the stored run too)."""
        if self._run is not None:
            self._store.discard(self._run)
        self._run, self._run_rows, self._pending, self._pending_rows = None, 0, [], 0

    def __len__(self) -> int:
        """Voxels held (the stored run, plus the rows still pending)."""
        return self._run_rows + self._pending_rows

    @property
    def nbytes_in_memory(self) -> int:
        """Bytes of the arrays this process holds for these sums (the pending rows; the run too in memory)."""
        parts = self._pending + ([self._run] if isinstance(self._run, Contribution) else [])
        return sum(a.nbytes for p in parts for a in (p.keys, p.weight, p.xyz, p.codes, p.colours, p.count)
                   if a is not None)
