"""Numbers to ASCII text, a whole table at once: the formatting of text outputs that hold millions of numbers
(a long stream's COLMAP model holds ~5 M observations; `repr` of each costs ~1 µs, 9 s of its end of stream).

Each number is written in fixed point with a column's number of decimals, so the text is what
``np.round(value, decimals)`` holds: where a binary twin of the file stores the values rounded the same way, the
two agree exactly (strtod and the division in np.round both round correctly to the nearest double).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

_MINUS, _POINT, _SPACE, _ZERO = (ord(c) for c in "-. 0")


def format_rows(columns: Sequence[np.ndarray], decimals: Sequence[int]) -> tuple[bytes, np.ndarray]:
    """The rows of a table given as its ``columns`` (each (n,)) as text: column j with ``decimals[j]`` digits
    after the point (0: an integer, no point), every number followed by one space. Returns the text and the byte
    offset where each row starts (n + 1,), so rows i..j-1 are ``text[offsets[i]:offsets[j] - 1]`` without their
    last space.

    Values must round to integers below 2**63 once scaled by their column's 10**decimals."""
    columns = [np.asarray(c) for c in columns]
    if len(columns) != len(decimals) or len({c.shape for c in columns}) > 1 or any(c.ndim != 1 for c in columns):
        raise ValueError(f"{len(decimals)} columns of one length (n,) expected, got shapes "
                         f"{[c.shape for c in columns]}")
    n = len(columns[0]) if columns else 0
    blocks = [_column_chars(c, d) for c, d in zip(columns, decimals)]
    # built a character position at a time, (width, n): each digit is one contiguous row, and the rows are
    # turned into lines once, by the selection (1.5x faster than writing strided (n, width) columns)
    chars = np.concatenate([b[0] for b in blocks]).T if blocks else np.zeros((n, 0), np.uint8)
    keep = np.concatenate([b[1] for b in blocks]).T if blocks else np.zeros((n, 0), bool)
    offsets = np.zeros(n + 1, np.int64)
    np.cumsum(np.count_nonzero(keep, axis=1), out=offsets[1:])
    return chars[keep].tobytes(), offsets


def _column_chars(values: np.ndarray, decimals: int) -> tuple[np.ndarray, np.ndarray]:
    """(width, n) ASCII of one column, a character position per row: sign, digits, point, decimals, space; and
    which to keep: the sign where negative, no leading zeros before the units digit."""
    if values.dtype.kind in "iu" and decimals == 0:
        scaled = values.astype(np.int64)
    else:
        scaled = np.rint(np.asarray(values, np.float64) * 10.0 ** decimals)
        if len(scaled) and not (np.all(np.isfinite(scaled)) and np.abs(scaled).max() < 2.0 ** 63):
            raise ValueError("values must be finite and below 2**63 / 10**decimals to be written in fixed point")
        scaled = scaled.astype(np.int64)
    magnitude = np.abs(scaled).astype(np.uint64)
    top = int(magnitude.max()) if len(magnitude) else 0
    if top < 2**32:  # 32-bit division is ~1.6x faster, and pixel coordinates to 1e-6 px fit
        magnitude = magnitude.astype(np.uint32)
    digits = max(len(str(top)), decimals + 1)
    point = 1 if decimals else 0
    chars = np.empty((1 + digits + point + 1, len(values)), np.uint8)
    chars[0] = _MINUS
    chars[-1] = _SPACE
    units = digits - decimals  # positions of the integer part
    ten = magnitude.dtype.type(10)
    for i in range(digits - 1, -1, -1):  # least significant first
        magnitude, digit = np.divmod(magnitude, ten)
        np.add(digit, _ZERO, out=chars[1 + i + (point if i >= units else 0)], casting="unsafe")
    if point:
        chars[1 + units] = _POINT
    keep = np.ones(chars.shape, bool)
    keep[0] = scaled < 0
    # leading zeros go, up to the units digit: a position is kept once a nonzero digit came before or at it
    np.logical_or.accumulate(chars[1:units] != _ZERO, axis=0, out=keep[1:units])
    return chars, keep
