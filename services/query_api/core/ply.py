"""Binary little-endian PLY of coloured points, built as bytes (header and vertex blocks apart, so a
response can stream the header first and the vertices chunk by chunk)."""
from __future__ import annotations

import numpy as np

VERTEX = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
LABELLED = np.dtype(VERTEX.descr + [("label", "<i4"), ("score", "<f4")])


def header(n_points: int, labelled: bool = False, comment: str = "") -> bytes:
    """PLY header for ``n_points`` vertices: x y z (float32), red green blue (uint8)[, label int32, score float32]."""
    if n_points < 0:
        raise ValueError(f"n_points must be >= 0, got {n_points}")
    lines = ["ply", "format binary_little_endian 1.0"]
    if comment:
        lines.append("comment " + " ".join(comment.split()))
    lines += [f"element vertex {n_points}", "property float x", "property float y", "property float z",
              "property uchar red", "property uchar green", "property uchar blue"]
    if labelled:
        lines += ["property int label", "property float score"]
    return ("\n".join(lines + ["end_header"]) + "\n").encode("ascii")


def vertices(xyz: np.ndarray, rgb: np.ndarray, label: np.ndarray | None = None, score: np.ndarray | None = None) -> bytes:
    """Vertex block: xyz (N, 3) float, rgb (N, 3) uint8[, label (N,) int, score (N,) float] → bytes."""
    xyz, rgb = np.asarray(xyz), np.asarray(rgb)
    n = len(xyz)
    if xyz.shape != (n, 3) or rgb.shape != (n, 3):
        raise ValueError(f"xyz and rgb must be (N, 3), got {xyz.shape} and {rgb.shape}")
    labelled = label is not None
    out = np.empty(n, LABELLED if labelled else VERTEX)
    out["x"], out["y"], out["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    out["red"], out["green"], out["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    if labelled:
        if score is None or np.shape(label) != (n,) or np.shape(score) != (n,):
            raise ValueError("label and score must both be (N,) when either is given")
        out["label"], out["score"] = label, score
    return out.tobytes()


def read(data: bytes) -> np.ndarray:
    """Parse what :func:`header` + :func:`vertices` wrote → structured array (for tests and clients)."""
    end = data.index(b"end_header\n") + len(b"end_header\n")
    head = data[:end].decode("ascii").splitlines()
    n = int(next(line for line in head if line.startswith("element vertex")).split()[-1])
    dtype = LABELLED if "property int label" in head else VERTEX
    if end + n * dtype.itemsize != len(data):
        raise ValueError(f"PLY body is {len(data) - end} bytes, header announces {n} vertices")
    return np.frombuffer(data, dtype, count=n, offset=end)
