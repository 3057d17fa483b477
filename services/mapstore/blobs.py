"""The map store's arrays as SQLite blobs: .npy bytes (dtype and shape included), read back without numpy's
per-call header parsing.
"""

from __future__ import annotations

import functools
import io
import struct

import numpy as np


def to_blob(array: np.ndarray | None) -> bytes | None:
    """Serialise an array (dtype and shape included) as .npy bytes; None stays None."""
    if array is None:
        return None
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(array), allow_pickle=False)
    return buf.getvalue()


def from_blob(blob: bytes | None) -> np.ndarray | None:
    """Inverse of `to_blob` (a writable array). The header's layout is parsed once per distinct header: np.load
    parses it with ``ast`` every time, most of reading a keyframe's small maps (the end of stream's export reads
    every stored keyframe's; a restart loads them all)."""
    if blob is None:
        return None
    if blob[:6] != b"\x93NUMPY":
        raise ValueError(f"not an .npy blob (it starts {blob[:8]!r})")
    size = _NPY_HEADER_SIZE.get(blob[6:7])
    if size is None:  # a newer .npy version than numpy's 1.0 and 2.0 (utf-8 headers): numpy reads it
        return np.load(io.BytesIO(blob), allow_pickle=False)
    offset = 8 + size.size + size.unpack_from(blob, 8)[0]
    dtype, shape, fortran = _npy_layout(blob[:offset])
    array = np.frombuffer(blob, dtype, count=int(np.prod(shape)), offset=offset).copy()
    return array.reshape(shape[::-1]).T if fortran else array.reshape(shape)


_NPY_HEADER_SIZE = {b"\x01": struct.Struct("<H"), b"\x02": struct.Struct("<I")}  # header length, by major version


@functools.lru_cache(maxsize=256)
def _npy_layout(header: bytes) -> tuple[np.dtype, tuple[int, ...], bool]:
    """(dtype, shape, fortran order) of an .npy header (magic and version included)."""
    f = io.BytesIO(header)
    major, _ = np.lib.format.read_magic(f)
    read = np.lib.format.read_array_header_1_0 if major == 1 else np.lib.format.read_array_header_2_0
    shape, fortran, dtype = read(f)
    if dtype.hasobject:
        raise ValueError("object arrays are not stored")
    return dtype, shape, fortran
