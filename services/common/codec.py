"""msgpack codec with numpy arrays as an extension type.

An array travels as ext type 1 whose data is ``msgpack([dtype.str, shape]) + raw bytes`` (C order). Decoding
wraps the payload bytes with ``np.frombuffer`` (no copy; the result is read-only), so a frame is copied once
into the payload and never again on the way in.
"""
from __future__ import annotations

import re
from typing import Any

import msgpack
import numpy as np

from .errors import DecodeError

ARRAY_EXT = 1
_ALLOWED_KINDS = "biuf"  # bool, signed, unsigned, float — no object arrays ever cross the wire
_DTYPE = re.compile(r"^[<>|=]?[biuf](1|2|4|8)$")


def _default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind not in _ALLOWED_KINDS:
            raise TypeError(f"cannot encode array of dtype {obj.dtype}")
        arr = obj if obj.flags.c_contiguous else obj.copy(order="C")
        header = msgpack.packb([arr.dtype.str, list(arr.shape)])
        return msgpack.ExtType(ARRAY_EXT, header + arr.tobytes())
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"cannot encode {type(obj).__name__}")


def _ext_hook(code: int, data: bytes) -> Any:
    if code != ARRAY_EXT:
        raise DecodeError(f"unknown msgpack extension type {code}")
    unpacker = msgpack.Unpacker(raw=False, max_buffer_size=len(data))
    unpacker.feed(data)
    try:
        dtype_str, shape = unpacker.unpack()
    except Exception as exc:  # malformed header: anything msgpack can raise
        raise DecodeError(f"bad array header: {exc}") from exc
    if not isinstance(dtype_str, str) or not _DTYPE.match(dtype_str):
        raise DecodeError(f"array dtype {dtype_str!r} not allowed")
    dtype = np.dtype(dtype_str)
    if dtype.kind not in _ALLOWED_KINDS or not isinstance(shape, list):
        raise DecodeError(f"array dtype {dtype_str!r} / shape {shape!r} not allowed")
    if any(not isinstance(n, int) or n < 0 for n in shape):
        raise DecodeError(f"bad array shape {shape!r}")
    offset = unpacker.tell()
    count = int(np.prod(shape, dtype=np.int64)) if shape else 1
    if len(data) - offset != count * dtype.itemsize:
        raise DecodeError(f"array of shape {shape} {dtype} needs {count * dtype.itemsize} bytes, got {len(data) - offset}")
    return np.frombuffer(data, dtype=dtype, count=count, offset=offset).reshape(tuple(shape))


def pack(obj: Any) -> bytes:
    """Encode a tree of dicts/lists/scalars/bytes/numpy arrays."""
    return msgpack.packb(obj, default=_default, use_bin_type=True)


def unpack(payload: bytes | bytearray | memoryview) -> Any:
    """Decode :func:`pack` output; raises :class:`DecodeError` for anything that is not valid."""
    try:
        return msgpack.unpackb(payload, ext_hook=_ext_hook, raw=False, strict_map_key=True)
    except DecodeError:
        raise
    except Exception as exc:  # msgpack raises many types for truncated/garbage input
        raise DecodeError(f"not a valid msgpack payload: {type(exc).__name__}: {exc}") from exc
