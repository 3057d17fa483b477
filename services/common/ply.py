"""The PLY layouts of the map and the one PLY writer and reader, for the mapstore's export (a file) and the gateway
(a response, streamed: the header for the announced count first, then each chunk's vertex block as it arrives).

Written here rather than with plyfile, the usual library: plyfile is GPL-3.0-or-later, which this Apache-2.0
package would pass on to everyone who ships it (the service images), it needs numpy >= 2, and it writes a whole
``PlyData`` held in memory, where the gateway streams a map it never holds whole. A vertex-only PLY is a header and
packed little-endian records; tests/test_ply.py holds that these bytes are the ones plyfile writes and reads.
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterable

import numpy as np

POINT = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
VERTEX = np.dtype(POINT)
"""A coloured point: float x y z (world, metres or the map's scale), uchar red green blue."""
LABEL_COLOURED = np.dtype(POINT + [("label_red", "u1"), ("label_green", "u1"), ("label_blue", "u1")])
"""The export's map.ply with each point's label as a colour (viewers show it as a second colour set)."""
SCORED = np.dtype(POINT + [("label", "<i4"), ("score", "<f4")])
"""The gateway's segmentation: each point's label index (-1 = none) and its cosine score."""

_PLY_TYPES = {"f4": "float", "f8": "double", "u1": "uchar", "i1": "char", "u2": "ushort", "i2": "short",
              "u4": "uint", "i4": "int"}
_NUMPY_TYPES = {name: "<" + code for code, name in _PLY_TYPES.items()} | {
    "float32": "<f4", "float64": "<f8", "uint8": "<u1", "int8": "<i1", "uint16": "<u2", "int16": "<i2",
    "uint32": "<u4", "int32": "<i4"}
_END = b"end_header\n"


def records(dtype: np.dtype, xyz: np.ndarray, rgb: np.ndarray, **fields: np.ndarray) -> np.ndarray:
    """(N,) structured array of ``dtype`` from xyz (N, 3), rgb (N, 3) and one (N,) array per other field."""
    xyz, rgb = np.asarray(xyz), np.asarray(rgb)
    n = len(xyz)
    if xyz.shape != (n, 3) or rgb.shape != (n, 3):
        raise ValueError(f"xyz and rgb must be (N, 3), got {xyz.shape} and {rgb.shape}")
    if set(dtype.names) - set(VERTEX.names) != set(fields):
        raise ValueError(f"fields {sorted(fields)} do not match the layout {dtype.names}")
    out = np.empty(n, dtype)
    for i, axis in enumerate("xyz"):
        out[axis] = xyz[:, i]
    for i, channel in enumerate(("red", "green", "blue")):
        out[channel] = rgb[:, i]
    for name, values in fields.items():
        if np.shape(values) != (n,):
            raise ValueError(f"{name} must be ({n},), got {np.shape(values)}")
        out[name] = values
    return out


def header(dtype: np.dtype, n_points: int, comments: Iterable[str] = (), text: bool = False) -> bytes:
    """The header of a PLY of ``n_points`` records of ``dtype``: binary little-endian, or ascii when ``text``."""
    if n_points < 0:
        raise ValueError(f"n_points must be >= 0, got {n_points}")
    lines = ["ply", f"format {'ascii' if text else 'binary_little_endian'} 1.0"]
    lines += ["comment " + " ".join(c.split()) for c in comments]  # a comment is one header line
    lines.append(f"element vertex {n_points}")
    lines += [f"property {_PLY_TYPES[dtype[name].str[1:]]} {name}" for name in dtype.names]
    return ("\n".join(lines) + "\n").encode("ascii") + _END


def vertex_block(vertices: np.ndarray) -> bytes:
    """The body bytes of ``vertices`` (a structured array of one of the layouts) in a binary PLY."""
    return np.ascontiguousarray(vertices).tobytes()


def write(path: Path, vertices: np.ndarray, text: bool = False, comments: Iterable[str] = ()) -> Path:
    """Write a vertex-only PLY: binary little-endian, or ascii when ``text``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        f.write(header(vertices.dtype, len(vertices), comments, text))
        if text:
            rows = (" ".join(f"{v:.9g}" if isinstance(v, float) else str(v) for v in row) for row in vertices.tolist())
            f.write("".join(row + "\n" for row in rows).encode("ascii"))
        else:
            f.write(vertex_block(vertices))
    return path


def read(source: Path | bytes) -> np.ndarray:
    """The vertices of a vertex-only PLY (binary little-endian or ascii, scalar properties), from a path or its
    bytes, as a structured array; ValueError when it is not one or its body does not hold what its header says."""
    data = bytes(source) if isinstance(source, (bytes, bytearray)) else Path(source).read_bytes()
    end = data.find(_END)
    head = data[:max(end, 0)].decode("ascii", "replace").splitlines()
    if end < 0 or not head or head[0] != "ply":
        raise ValueError("not a vertex PLY: no 'ply' ... 'end_header' header")
    fmt = next((line.split()[1] for line in head if line.startswith("format ")), "")
    elements = [line.split() for line in head if line.startswith("element ")]
    if fmt not in ("ascii", "binary_little_endian") or [e[1] for e in elements] != ["vertex"]:
        raise ValueError(f"not a vertex PLY this reader knows: format {fmt!r}, elements {elements}")
    n = int(elements[0][2])
    props = [line.split() for line in head if line.startswith("property ")]
    if any(len(p) != 3 or p[1] not in _NUMPY_TYPES for p in props):
        raise ValueError(f"only scalar properties are read, got {props}")
    dtype = np.dtype([(p[2], _NUMPY_TYPES[p[1]]) for p in props])
    body = data[end + len(_END):]
    if fmt == "ascii":
        rows = body.decode("ascii").split("\n")[:n]
        if len(rows) < n or (n and not rows[-1].strip()):
            raise ValueError(f"PLY body too short: the header announces {n} vertices")
        return np.array([tuple(r.split()) for r in rows], dtype=[(p, "U32") for p in dtype.names]).astype(dtype)
    if len(body) != n * dtype.itemsize:
        raise ValueError(f"PLY body is {len(body)} bytes, the header announces {n} vertices of {dtype.itemsize}")
    return np.frombuffer(body, dtype, count=n)
