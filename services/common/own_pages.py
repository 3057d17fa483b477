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

import numpy as np


def own_pages(array: np.ndarray) -> np.ndarray:
    """A writable copy of ``array`` in a memory map of its own (released with the last reference to it)."""
    array = np.asarray(array)
    if array.nbytes == 0:
        return array.copy()
    pages = mmap.mmap(-1, array.nbytes)
    kept = np.frombuffer(pages, dtype=array.dtype, count=array.size).reshape(array.shape)
    kept[...] = array
    return kept

