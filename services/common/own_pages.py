"""Arrays kept for a long time, on pages of their own instead of the general heap.

A process that alternates bursts of short-lived buffers (a BA's per-slice fields) with long-lived arrays made
between the bursts (cached flow targets, keyframe images and codes) fragments glibc's heap: the long-lived arrays
land in the holes a burst left, and the next burst, finding no hole large enough, touches fresh pages while the
holes stay resident. A copy in an anonymous memory map of its own keeps such an array out of the heap, and its
pages go back to the kernel when it is freed.

Each array is one mapping (rounded up to whole pages): for arrays of kilobytes and more that live across bursts,
not for every temporary. ba holds ~7,000 such mappings on the 10,000-frame stream, against the kernel's default
limit of 65,530 (``vm.max_map_count``)."""
from __future__ import annotations

import mmap
import sys
from typing import Sequence

import numpy as np

_MAP_NORESERVE = 0x4000 if sys.platform.startswith("linux") else 0  # no swap accounted for the untouched part


def lazy_zeros(shape: tuple[int, ...], dtype) -> np.ndarray:
    """A zeroed array in an anonymous memory map of its own: the kernel gives a page memory when it is first
    written, so an array reserved far larger than it is used costs the memory of the part in use, and freeing it
    returns its pages at once instead of leaving a hole in the heap. Plain zeros where the map cannot be made
    (strict overcommit, or the kernel's limit of maps)."""
    size = int(np.prod(shape))
    try:
        buffer = mmap.mmap(-1, max(size * np.dtype(dtype).itemsize, 1),
                           flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS | _MAP_NORESERVE)
    except OSError:
        return np.zeros(shape, dtype)
    return np.frombuffer(buffer, dtype, count=size).reshape(shape)


def own_pages(array: np.ndarray, dtype=None) -> np.ndarray:
    """A writable copy of ``array`` (cast to ``dtype`` if given) in a memory map of its own (released with the last
    reference to it; a heap copy where no map can be made, e.g. at the kernel's limit of maps)."""
    array = np.asarray(array)
    dtype = array.dtype if dtype is None else np.dtype(dtype)
    if array.size == 0:
        return array.astype(dtype)
    kept = lazy_zeros(array.shape, dtype)
    kept[...] = array
    return kept


_PACKED_ALIGN = 64  # bytes: each array of a pack starts where SIMD loads of any dtype are aligned


def own_pages_packed(arrays: Sequence[np.ndarray | None]) -> list[np.ndarray | None]:
    """Writable copies of ``arrays`` side by side in one memory map of their own (None stays None): for arrays
    that are made and dropped together, such as a keyframe's voxel sums, at the cost of one map instead of one
    each. The map lives until the last of the copies is dropped."""
    arrays = [None if a is None else np.asarray(a) for a in arrays]
    offsets, total = [], 0
    for a in arrays:
        offsets.append(total)
        if a is not None:
            total += -(-a.nbytes // _PACKED_ALIGN) * _PACKED_ALIGN
    buffer = lazy_zeros((max(total, 1),), np.uint8)
    packed: list[np.ndarray | None] = []
    for a, offset in zip(arrays, offsets):
        if a is None:
            packed.append(None)
            continue
        kept = buffer[offset : offset + a.nbytes].view(a.dtype).reshape(a.shape)
        kept[...] = a
        packed.append(kept)
    return packed


def release_rows(array: np.ndarray, first_row: int, written_rows: int | None = None) -> int:
    """Zero rows ``first_row:`` of a `lazy_zeros` array and give the kernel back the whole pages past them, so that
    a reserved array whose use shrank costs the memory of its rows in use again (they read as zeros, and cost
    memory again once written). ``written_rows``: rows past it were never written (only the ones before it are
    zeroed: zeroing the rest of a reserve would make it resident). Returns the bytes handed back: 0 for an array on
    the heap (only zeroed), and where the kernel cannot take them."""
    first_row = max(0, min(first_row, array.shape[0]))
    array[first_row:written_rows] = 0
    buffer = array
    while buffer is not None and not isinstance(buffer, mmap.mmap):  # views, then numpy's memoryview of the map
        buffer = buffer.obj if isinstance(buffer, memoryview) else getattr(buffer, "base", None)
    if buffer is None or not array.flags.c_contiguous or not hasattr(mmap, "MADV_DONTNEED"):
        return 0
    offset = array.ctypes.data - np.frombuffer(buffer, np.uint8, count=1).ctypes.data  # a packed array's place
    start = -(-(offset + first_row * array.strides[0]) // mmap.PAGESIZE) * mmap.PAGESIZE  # first whole page
    end = offset + array.nbytes
    if end < len(buffer):  # another array of the pack follows: its first page stays
        end = end // mmap.PAGESIZE * mmap.PAGESIZE
    length = end - start
    if length <= 0:
        return 0
    try:
        buffer.madvise(mmap.MADV_DONTNEED, start, length)
    except OSError:
        return 0
    return length
