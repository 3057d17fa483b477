"""Validation of a decoded message map against its dataclass (:mod:`services.common.schema`): field types, array
dtypes and shapes (with dimensions named across fields), the session name, then the message's own ``check``. Every
failure is a :class:`DecodeError` that names the message kind and the field."""
from __future__ import annotations

import dataclasses
import functools
import re
import types
import typing
from typing import TYPE_CHECKING, Any, Union

import numpy as np

from .errors import DecodeError

if TYPE_CHECKING:
    from .schema import Message

MAX_DIM = 1 << 16  # no image side or list length on the wire is larger
SESSION_NAME = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")  # a name, as keys.check_name: it is a key segment too


def arr(dtypes: str, shape: tuple) -> dict:
    """Field metadata for an array: allowed dtype chars (e.g. ``"u1"``, ``"f4 f8"``) and a shape pattern
    whose entries are ints, ``None`` (any) or names shared between fields (must agree within a message)."""
    return {"dtypes": tuple(np.dtype(d) for d in dtypes.split()), "shape": shape}


@functools.cache
def _hints(cls: type[Message]) -> dict[str, Any]:
    """The field types of a message class, resolved once (``get_type_hints`` costs ~0.1 ms, on every decode)."""
    return typing.get_type_hints(cls)


def from_dict(cls: type[Message], body: dict) -> Message:
    """Build and validate ``cls`` from a decoded map (unknown keys are ignored: newer minor fields)."""
    hints = _hints(cls)
    dims: dict[str, int] = {}
    values = {}
    for f in dataclasses.fields(cls):
        if f.name not in body:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise DecodeError(f"{cls.KIND}: missing field '{f.name}'")
            continue
        values[f.name] = _check_field(cls.KIND, f, hints[f.name], body[f.name], dims)
    if values.get("session") and not SESSION_NAME.match(values["session"]):
        raise DecodeError(f"{cls.KIND}: field 'session' must be 1-64 of A-Z a-z 0-9 _ -, got {values['session']!r}")
    msg = cls(**values)
    msg.check()
    return msg


def _check_field(kind: str, f: dataclasses.Field, hint: Any, value: Any, dims: dict[str, int]) -> Any:
    optional = typing.get_origin(hint) in (Union, types.UnionType) and type(None) in typing.get_args(hint)
    base = next(a for a in typing.get_args(hint) if a is not type(None)) if optional else hint
    if value is None:
        if optional:
            return None
        raise DecodeError(f"{kind}: field '{f.name}' must not be null")
    if base is np.ndarray:
        return _check_array(kind, f.name, value, f.metadata, dims)
    ok = {
        int: lambda v: isinstance(v, int) and not isinstance(v, bool) and abs(v) < 1 << 63,
        float: lambda v: isinstance(v, (int, float)) and not isinstance(v, bool),
        bool: lambda v: isinstance(v, bool),
        str: lambda v: isinstance(v, str) and len(v) <= 4096,
        bytes: lambda v: isinstance(v, (bytes, bytearray)),
    }[base]
    if not ok(value):
        raise DecodeError(f"{kind}: field '{f.name}' must be {base.__name__}, got {type(value).__name__}")
    return float(value) if base is float else value


def _check_array(kind: str, name: str, value: Any, meta: Any, dims: dict[str, int]) -> np.ndarray:
    if not isinstance(value, np.ndarray):
        raise DecodeError(f"{kind}: field '{name}' must be an array, got {type(value).__name__}")
    if value.dtype not in meta["dtypes"]:
        allowed = ", ".join(str(d) for d in meta["dtypes"])
        raise DecodeError(f"{kind}: field '{name}' has dtype {value.dtype}, expected {allowed}")
    pattern = meta["shape"]
    if value.ndim != len(pattern):
        raise DecodeError(f"{kind}: field '{name}' has shape {value.shape}, expected {len(pattern)} dims {pattern}")
    for n, want in zip(value.shape, pattern):
        if n > MAX_DIM:
            raise DecodeError(f"{kind}: field '{name}' dimension {n} exceeds {MAX_DIM}")
        if isinstance(want, int) and n != want:
            raise DecodeError(f"{kind}: field '{name}' has shape {value.shape}, expected {pattern}")
        if isinstance(want, str) and dims.setdefault(want, n) != n:
            raise DecodeError(f"{kind}: field '{name}' dimension {want}={n} disagrees with {dims[want]}")
    return value
