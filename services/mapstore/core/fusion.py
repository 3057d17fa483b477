"""Incremental voxel fusion: weighted sums per voxel that keyframes add to and subtract from.

Each keyframe's contribution (its voxel keys and per-voxel sums) is kept, so a keyframe whose pose or
depth changed is re-fused by subtracting its old contribution and adding the new one; nothing else is
touched. Sums are float64 (positions, weights) and float32 (codes, colours); a voxel whose
observation count drops to zero is cleared exactly, so rounding does not accumulate in empty voxels.

A contribution keeps its code sums in the PCA version its keyframe was coded with; the grid holds them in the
map's current version, each contribution entering through the affine map of its version (Σw·z ↦ MΣw·z + cΣw,
``services/common/pca_codes.py``). A new version re-sums the grid's codes from the contributions (`recode`).

A keyframe whose codes have not arrived contributes geometry and colours only (``codes`` None): code sums have
their own weight and point count per voxel, so a voxel seen only by such keyframes has no code (NaN in
`FusedVoxels.codes`, ``code_weight`` 0) rather than the zero code, which would decode to the PCA mean.

Folded keyframes (final: no later change can reach them, ``core/map.py``) hand their contribution to the
frozen sums of their PCA version (core/frozen.py): one merged run per version whose size follows the map (its
voxels), not the number of keyframes. The grid treats it like any other contribution (a new basis re-sums it
through its version's map, a chunk at a time), so folding alone does not change the fused map (snapping at the
fold does: core/snapping.py).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Iterable, NamedTuple

import numpy as np

from services.common.own_pages import lazy_zeros, own_pages_packed, release_rows
from services.common.pca_codes import CodeMap, convert_sums
from services.mapstore.core.slot_table import SlotTable

_KEY_BITS = 21
_KEY_OFFSET = 1 << (_KEY_BITS - 1)
_KEY_MASK = (1 << _KEY_BITS) - 1


def voxel_keys(ijk: np.ndarray) -> np.ndarray:
    """Pack integer voxel coordinates (N, 3) int64 (each in ±2^20) into (N,) int64 keys."""
    shifted = ijk.astype(np.int64) + _KEY_OFFSET
    if shifted.size and (shifted.min() < 0 or shifted.max() > _KEY_MASK):
        raise ValueError("voxel coordinates exceed ±2^20; use a larger voxel size")
    return (shifted[:, 0] << (2 * _KEY_BITS)) | (shifted[:, 1] << _KEY_BITS) | shifted[:, 2]


def voxel_coords(keys: np.ndarray) -> np.ndarray:
    """Inverse of `voxel_keys`: (N,) int64 keys → (N, 3) int64 voxel coordinates."""
    k = keys.astype(np.int64)
    ijk = np.stack([(k >> (2 * _KEY_BITS)) & _KEY_MASK, (k >> _KEY_BITS) & _KEY_MASK, k & _KEY_MASK], axis=1)
    return ijk - _KEY_OFFSET


@dataclass(frozen=True)
class Contribution:
    """One keyframe's per-voxel sums (M distinct voxels).

    Fields: keys (M,) int64; weight (M,) float64 Σw; xyz (M, 3) float64 Σw·x (world);
    codes (M, K) float32 Σw·z, or None for a keyframe without codes (geometry only); colours (M, 3) float32
    Σw·rgb; count (M,) int64 points.
    """

    keys: np.ndarray
    weight: np.ndarray
    xyz: np.ndarray
    codes: np.ndarray | None
    colours: np.ndarray
    count: np.ndarray

    def on_own_pages(self) -> "Contribution":
        """The same sums in one memory map of their own, for a contribution the map keeps until its keyframe is
        re-fused (`own_pages_packed`). Re-fusion made and dropped these arrays (~0.4 MB a keyframe, a different
        size each time) tens of thousands of times on the 10,000-frame stream, and they cut the heap into holes
        that nothing else fit: its free part grew 43 -> 62 MB after frame 1,000 (docs/BENCHMARKS.md)."""
        return Contribution(*own_pages_packed([getattr(self, f.name) for f in fields(self)]))


def make_contribution(
    points_world: np.ndarray, weight: np.ndarray, codes: np.ndarray | None, colours: np.ndarray, voxel_size: float
) -> Contribution:
    """Sum one keyframe's points per voxel.

    Args:
        points_world: (M, 3) float64 world points.
        weight: (M,) float point weights (> 0).
        codes: (M, K) float codes, or None (a keyframe without codes); colours: (M, 3) uint8/float RGB.
        voxel_size: voxel edge in world units.
    Returns:
        Contribution over the distinct voxels the points fall in.
    """
    n = points_world.shape[0]
    if weight.shape != (n,) or (codes is not None and codes.shape[0] != n) or colours.shape != (n, 3):
        raise ValueError("points, weight, codes and colours must have the same length")
    w = weight.astype(np.float64)
    weighted = Contribution(  # one row per point: its weighted values, summed per voxel next
        keys=voxel_keys(np.floor(points_world / voxel_size).astype(np.int64)),
        weight=w,
        xyz=points_world.astype(np.float64) * w[:, None],
        codes=None if codes is None else (codes.astype(np.float32) * w[:, None]).astype(np.float32),
        colours=(colours.astype(np.float32) * w[:, None]).astype(np.float32),
        count=np.ones(n, np.int64),
    )
    return sum_by_key(weighted)


def merge_contributions(parts: list[Contribution]) -> Contribution:
    """One contribution with the per-voxel sums of ``parts`` (all with codes of one K, or all without codes)."""
    parts = [p for p in parts if p.keys.size] or parts[:1]
    if len(parts) == 1:
        return parts[0]
    with_codes = parts[0].codes is not None
    if any((p.codes is not None) != with_codes for p in parts):
        raise ValueError("cannot merge contributions with and without codes")
    return _summed(parts)


def sum_by_key(c: Contribution) -> Contribution:
    """``c`` with the rows that share a key summed into one (keys ascending; sums added in float64)."""
    return _summed([c])


SUM_COLUMNS = 8  # columns of a field sorted and summed at once: a whole field's sorted float64 copy was 5x the
# result's memory at the merge of a 70,000-voxel folded map (66 MB for 13 MB), the mapstore's high-water as it grew
RECODE_ROWS = 16384  # rows of a contribution converted into a new PCA version at once (VoxelGrid.recode)


def _summed(parts: list[Contribution]) -> Contribution:
    """The rows of ``parts`` taken together, those that share a key summed into one (keys ascending), a few
    columns at a time; each sum accumulates in float64 (int64 for counts) in row order."""
    keys = parts[0].keys if len(parts) == 1 else np.concatenate([p.keys for p in parts])
    order = np.argsort(keys, kind="stable")
    sk = keys[order]
    starts = np.flatnonzero(np.r_[True, sk[1:] != sk[:-1]]) if sk.size else np.zeros(0, np.int64)

    def total(name: str) -> np.ndarray | None:
        arrays = [getattr(p, name) for p in parts]
        if arrays[0] is None:
            return None
        if not sk.size:
            return np.concatenate(arrays)
        first = arrays[0]
        accumulate = np.int64 if first.dtype == np.int64 else np.float64
        out = np.empty((starts.size, *first.shape[1:]), first.dtype)
        width = first.shape[1] if first.ndim == 2 else 1
        for col in range(0, width, SUM_COLUMNS):
            cols = slice(col, col + SUM_COLUMNS) if first.ndim == 2 else slice(None)
            rows = first[..., cols] if len(arrays) == 1 else np.concatenate([a[..., cols] for a in arrays])
            out[..., cols] = np.add.reduceat(rows[order], starts, axis=0, dtype=accumulate)
        return out

    return Contribution(sk[starts], *(total(f.name) for f in fields(Contribution) if f.name != "keys"))


class FusedVoxels(NamedTuple):
    """The fused map: one point per occupied voxel (N voxels)."""

    keys: np.ndarray  # (N,) int64 voxel keys
    ijk: np.ndarray  # (N, 3) int64 voxel coordinates
    xyz: np.ndarray  # (N, 3) float64 weighted mean world position
    codes: np.ndarray  # (N, K) float32 weighted mean code of the points with codes; NaN where none has codes
    colours: np.ndarray  # (N, 3) uint8 weighted mean RGB
    weight: np.ndarray  # (N,) float64 summed weight
    count: np.ndarray  # (N,) int64 points fused
    code_weight: np.ndarray | None = None  # (N,) float64 summed weight of the points with codes (0: the voxel has
    # no code); None: every voxel has one (a map built elsewhere)


RESERVED_GRID_BYTES = 1 << 30  # address space a grown grid reserves for its slots (only written pages use memory)


class VoxelGrid:
    """Slot-based accumulators for voxel sums, keyed by packed voxel coordinates.

    A grid that outgrows its first ``initial_capacity`` slots reserves `RESERVED_GRID_BYTES` of slots in lazily
    backed arrays (`lazy_zeros`): slots are handed out in order (freed ones first), so memory follows the voxels in
    use, and growing does not copy. Growing by copies held the old and new arrays at once (the mapstore's
    10,000-frame map: 69,984 → 104,976 slots for 72,525 voxels at frame ~3,000) and left the old ones as a hole in
    the heap. When many voxels empty at once (a person carved away), `compact` moves the last slots into the holes
    and hands the pages past them back, so the memory follows the voxels again instead of the most ever held."""

    _FIELDS = ("_keys", "_weight", "_xyz", "_codes", "_colours", "_count", "_code_weight", "_code_count")

    def __init__(self, code_dim: int, initial_capacity: int = 4096) -> None:
        self.code_dim = code_dim
        self._slot_of = SlotTable()  # key -> slot (core/slot_table.py)
        self._free: list[int] = []
        self._used = 0
        self._alloc(initial_capacity, np.zeros)

    def _alloc(self, cap: int, zeros=lazy_zeros) -> None:
        old = getattr(self, "_weight", None)
        fields = {"_keys": ((cap,), np.int64), "_weight": ((cap,), np.float64), "_xyz": ((cap, 3), np.float64),
                  "_codes": ((cap, self.code_dim), np.float32), "_colours": ((cap, 3), np.float32),
                  "_count": ((cap,), np.int64), "_code_weight": ((cap,), np.float64),
                  "_code_count": ((cap,), np.int64)}
        for name, (shape, dtype) in fields.items():
            arr = zeros(shape, dtype)
            if old is not None:
                prev = getattr(self, name)
                arr[: self._used] = prev[: self._used]
            setattr(self, name, arr)

    def _slots(self, keys: np.ndarray) -> np.ndarray:
        """Slots of `keys`, creating the missing ones: freed slots first (the most recently freed first), then
        new ones past those handed out."""
        keys = np.asarray(keys, np.int64)
        slots = self._slot_of.lookup(keys)
        missing = slots < 0
        if missing.any():
            new, first, where = np.unique(keys[missing], return_index=True, return_inverse=True)
            given = np.empty(new.size, np.int64)
            given[np.argsort(first, kind="stable")] = self._take_slots(new.size)  # in order of first appearance
            self._keys[given] = new
            self._slot_of.insert(new, given)
            slots[missing] = given[where.reshape(-1)]
        return slots

    def _take_slots(self, n: int) -> np.ndarray:
        reused = min(n, len(self._free))
        taken = self._free[len(self._free) - reused:][::-1]
        del self._free[len(self._free) - reused:]
        return np.concatenate([np.asarray(taken, np.int64), self._new_slots(n - reused)])

    def _new_slots(self, n: int) -> np.ndarray:
        """``n`` slots past those handed out (the arrays reserved for them when they outgrow their first size)."""
        if self._used + n > self._keys.shape[0]:
            slot_bytes = 76 + 4 * self.code_dim  # the fields of _alloc
            self._alloc(max(self._keys.shape[0] * 3 // 2, 16, self._used + n, RESERVED_GRID_BYTES // slot_bytes))
        self._used += n
        return np.arange(self._used - n, self._used, dtype=np.int64)

    def _grid_codes(self, c: Contribution, cmap: CodeMap | None) -> np.ndarray:
        """A contribution's (M, K) code sums in the grid's version (``cmap``: from its own; None = the same)."""
        codes = c.codes if cmap is None or cmap.is_identity else convert_sums(c.codes, c.weight, cmap)
        if codes.shape[1:] != (self.code_dim,) and c.keys.size:
            raise ValueError(f"codes have {codes.shape[1]} channels, map has {self.code_dim}")
        return codes

    def apply(self, c: Contribution, sign: int, cmap: CodeMap | None = None) -> None:
        """Add (sign=+1) or subtract (sign=−1) a keyframe's contribution, its codes (if any) mapped by ``cmap``."""
        if c.codes is not None and c.keys.size and self.code_dim == 0:
            self.set_code_dim(c.codes.shape[1] if cmap is None else cmap.matrix.shape[0])
        codes = None if c.codes is None else self._grid_codes(c, cmap)
        slots = self._slots(c.keys)  # keys are distinct within a contribution: plain fancy indexing
        self._weight[slots] += sign * c.weight
        self._xyz[slots] += sign * c.xyz
        self._colours[slots] += sign * c.colours
        self._count[slots] += sign * c.count
        if codes is not None and c.keys.size:
            self._codes[slots] += sign * codes
            self._code_weight[slots] += sign * c.weight
            self._code_count[slots] += sign * c.count
            uncoded = slots[self._code_count[slots] <= 0]  # cleared exactly: no rounding residue poses as a code
            for arr in (self._codes, self._code_weight, self._code_count):
                arr[uncoded] = 0
        empty = slots[self._count[slots] <= 0]
        self._slot_of.remove(self._keys[empty])
        self._free.extend(empty.tolist())
        for arr in (self._weight, self._xyz, self._codes, self._colours, self._count, self._code_weight,
                    self._code_count):
            arr[empty] = 0

    def compact(self, min_free: int = 4096, min_share: float = 0.125) -> int:
        """If at least ``min_free`` slots and ``min_share`` of the slots handed out are free: move the voxels in the
        slots past ``len(self)`` into the free ones below it and release the rest (`release_rows`). The sums do not
        change, only where they are kept. Returns the slots released (0 when it did not compact)."""
        n, free = len(self._slot_of), len(self._free)
        if free < max(min_free, min_share * self._used):
            return 0
        holes = np.array(sorted(s for s in self._free if s < n), np.int64)
        is_free = np.zeros(self._used - n, bool)
        is_free[[s - n for s in self._free if s >= n]] = True
        moved = np.flatnonzero(~is_free) + n  # the voxels past n: as many as the holes below it
        for name in self._FIELDS:
            arr = getattr(self, name)
            arr[holes] = arr[moved]
        self._slot_of.assign(self._keys[holes], holes)
        released, used, self._used, self._free = self._used - n, self._used, n, []
        for name in self._FIELDS:
            release_rows(getattr(self, name), n, used)
        return released

    def set_code_dim(self, code_dim: int) -> None:
        """Give a grid that has no code sums yet (only keyframes without codes fused so far) its code size."""
        if self._code_count[: self._used].any():
            raise ValueError("the grid already holds code sums; use recode to change their size")
        self.code_dim = code_dim
        self._codes = lazy_zeros((self._keys.shape[0], code_dim), np.float32)

    def recode(self, parts: list[tuple[Iterable[Contribution], CodeMap | None]], code_dim: int) -> None:
        """Re-sum every voxel's codes in a new version (``code_dim`` = its K) from all the contributions with
        codes now applied, each with the map from its own version; weights, positions and colours are untouched.
        Each part is an iterable of contributions: a list is in memory (a live keyframe's one), its slots looked
        up once for all the column passes; any other iterable (frozen sums' chunks) is read anew, a few columns
        at a time. A few columns and rows at a time, into the grid's own code array where K is unchanged: the
        whole grid's float64 codes and each part's converted sums at once were several times the grid's codes, at
        every PCA refit of a growing map (the mapstore's high-water)."""
        coded = [(chunks, None if cmap is None or cmap.is_identity else cmap) for chunks, cmap in parts]
        if self._codes.shape[1] != code_dim:
            self._codes = None  # freed before its successor is allocated
            self._codes = lazy_zeros((self._keys.shape[0], code_dim), np.float32)
        self.code_dim = code_dim
        # int32, ~4 B a key: a lookup per pass was a third of a PCA refit's re-sum on KITTI 07
        live_slots = [[None if c.codes is None else self._slots(c.keys).astype(np.int32) for c in chunks]
                      if isinstance(chunks, list) else None for chunks, _ in coded]
        for col in range(0, code_dim, SUM_COLUMNS):
            cols = slice(col, min(col + SUM_COLUMNS, code_dim))
            block = np.zeros((self._used, cols.stop - cols.start), np.float64)  # slots past _used never given
            for (chunks, cmap), known in zip(coded, live_slots):
                for i, c in enumerate(chunks):
                    if c.codes is None:
                        continue
                    slots = self._slots(c.keys) if known is None else known[i]
                    for start in range(0, c.keys.size, RECODE_ROWS):
                        rows = slice(start, start + RECODE_ROWS)
                        block[slots[rows]] += (c.codes[rows, cols] if cmap is None
                                               else convert_sums(c.codes[rows], c.weight[rows], cmap, cols))
            self._codes[: self._used, cols] = block

    def __len__(self) -> int:
        return len(self._slot_of)

    def fused(self) -> FusedVoxels:
        """Weighted means of every occupied voxel, sorted by key (deterministic order)."""
        keys, slots = self._slot_of.items()
        slots = slots[np.argsort(keys, kind="stable")]
        w = self._weight[slots]
        inv = np.where(w > 0, 1.0 / np.where(w > 0, w, 1.0), 0.0)
        cw = self._code_weight[slots]
        coded = self._code_count[slots] > 0
        code_inv = np.where(coded, 1.0 / np.where(coded, cw, 1.0), np.nan)
        colours = np.clip(np.rint(self._colours[slots] * inv[:, None]), 0, 255).astype(np.uint8)
        keys = self._keys[slots]
        return FusedVoxels(keys, voxel_coords(keys), self._xyz[slots] * inv[:, None],
                           (self._codes[slots] * code_inv[:, None]).astype(np.float32), colours, w,
                           self._count[slots].copy(), cw.copy())
