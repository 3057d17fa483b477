"""The gateway's PLY responses, header and vertex blocks apart so a response can stream the header first and the
vertices chunk by chunk (layouts and why in :mod:`services.common.ply`)."""
from __future__ import annotations

import numpy as np

from ...common import ply
from ...common.ply import SCORED, VERTEX


def header(n_points: int, labelled: bool = False, comment: str = "") -> bytes:
    """PLY header for ``n_points`` vertices: x y z (float32), red green blue (uint8)[, label int32, score float32]."""
    return ply.header(SCORED if labelled else VERTEX, n_points, [comment] if comment else [])


def vertices(xyz: np.ndarray, rgb: np.ndarray, label: np.ndarray | None = None, score: np.ndarray | None = None) -> bytes:
    """Vertex block: xyz (N, 3) float, rgb (N, 3) uint8[, label (N,) int, score (N,) float] → bytes."""
    if (label is None) != (score is None):
        raise ValueError("label and score must both be (N,) when either is given")
    if label is None:
        return ply.vertex_block(ply.records(VERTEX, xyz, rgb))
    return ply.vertex_block(ply.records(SCORED, xyz, rgb, label=label, score=score))


read = ply.read
"""Parse what :func:`header` + :func:`vertices` wrote → structured array (for tests and clients)."""
