"""A field of every edge formed a slice of edges at a time (a BA linearised in slices: core/ba.py's
``_evaluate``), written into the buffer of the last evaluation so that no two generations of it exist at once."""
from __future__ import annotations

import torch


def join_slice(whole: torch.Tensor | None, part: torch.Tensor | None, edges: slice,
               n_edges: int) -> torch.Tensor | None:
    """A slice's field ``part`` written into the field of every edge ``whole`` at ``edges`` (allocated when None
    or not of its kind). A part that is one broadcast value (the fixed kernel's) gives a broadcast view; a kernel
    mask that is None (nowhere) in this slice is False there. ``part`` may be ``whole``'s own slice (an ARK cache
    edge kept): nothing to copy."""
    if part is None:
        if whole is not None:
            whole[edges] = False
        return whole
    if one_value(part):
        return part[:1].expand(n_edges, *part.shape[1:])  # irls.uniform's
    shape = (n_edges, *part.shape[1:])
    if whole is None or whole.shape != shape or whole.dtype != part.dtype or 0 in whole.stride():
        # a mask that first appears in a later slice is False in the slices before it
        whole = part.new_zeros(shape) if part.dtype == torch.bool else part.new_empty(shape)
    if part.data_ptr() != whole[edges].data_ptr():
        whole[edges] = part
    return whole


def one_value(field: torch.Tensor) -> bool:
    """Whether ``field`` is one value expanded to its shape (a broadcast view, no memory of its own)."""
    return 0 in field.stride() and all(st == 0 or n == 1 for st, n in zip(field.stride(), field.shape))
