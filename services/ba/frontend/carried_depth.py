"""Depth carried from one keyframe to another by their poses, and what mapping's refined depth says of it.

Tracking promotes keyframes of its own while mapping is behind, each with the depth of the one before carried over
(:func:`propagate_disparity`, as SVO and LSD-SLAM carry depth to a new keyframe); so its chain of keyframes drifts
in scale as well as in pose. When mapping's refined keyframe arrives, :func:`depth_scale` compares the two depths
and :func:`similarity_about` moves the chain onto mapping's pose and scale. numpy arrays in and out.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from services.ba.core import se3_numpy as se3
from services.ba.core.host_arrays import as_numpy

MIN_SCALE_CELLS = 0.1  # share of the grid the carried depth must cover for its scale to be compared
MAX_SCALE_FIX = 2.0  # one correction rescales a chain by at most this factor (either way)


def propagate_disparity(pose_from, pose_to, disparity, intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Grid disparity ``(h, w)`` of camera ``pose_to`` from camera ``pose_from``'s ``(h, w)`` grid disparity: each
    cell's point moved into the new camera and splatted to its nearest cell (the nearest point wins); cells no
    point lands in get the median of those that did. Poses world_from_cam ``(4, 4)``, grid intrinsics ``(4,)``
    (numpy arrays or torch tensors). Returns float64 (disparity, known): ``known`` is 1 where a point landed, 0
    where the median filled in."""
    disparity = as_numpy(disparity)
    h, w = disparity.shape
    fx, fy, cx, cy = (float(v) for v in as_numpy(intrinsics))
    ys, xs = np.meshgrid(np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64), indexing="ij")
    disp = np.maximum(disparity, 1e-6)
    points = np.stack([(xs - cx) / fx / disp, (ys - cy) / fy / disp, 1.0 / disp], axis=-1).reshape(-1, 3)
    to_from = se3.inverse(as_numpy(pose_to)) @ as_numpy(pose_from)
    moved = points @ to_from[:3, :3].T + to_from[:3, 3]
    z = moved[:, 2]
    front = z > 1e-6
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.round(moved[:, 0] / np.maximum(z, 1e-6) * fx + cx)
        v = np.round(moved[:, 1] / np.maximum(z, 1e-6) * fy + cy)
    inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    out = np.zeros(h * w)
    np.maximum.at(out, (v[inside] * w + u[inside]).astype(np.int64), 1.0 / z[inside])
    filled = out > 0
    fill = _lower_median(out[filled]) if filled.any() else _lower_median(disp.ravel())
    return np.where(filled, out, fill).reshape(h, w), filled.reshape(h, w).astype(np.float64)


def _lower_median(values: np.ndarray) -> float:
    """The lower of the two middle values for an even count (as torch's median: a value that occurs)."""
    return float(np.partition(values, (values.size - 1) // 2)[(values.size - 1) // 2])


def depth_scale(carried: np.ndarray, known: np.ndarray, mapped: np.ndarray) -> float:
    """Mapped depth over carried depth of one keyframe: the median ratio over the cells where a carried point landed
    (``known`` > 0), from ``(h, w)`` grid disparities ``carried`` and ``mapped``; 1 where fewer than
    ``MIN_SCALE_CELLS`` of the grid can say, bounded to ``MAX_SCALE_FIX`` either way. A rigid correction of a chain
    would keep its scale drift in every pose after the keyframe (KITTI 07 live first poses: step lengths 0.85-3.05x
    the truth's over 20 frames)."""
    cells = (known > 0) & (carried > 0) & (mapped > 0)
    if cells.mean() < MIN_SCALE_CELLS:
        return 1.0
    ratio = float(np.median(carried[cells] / mapped[cells]))
    return float(np.clip(ratio, 1.0 / MAX_SCALE_FIX, MAX_SCALE_FIX))


def similarity_about(mapped: np.ndarray, tracked: np.ndarray, scale: float) -> Callable[[np.ndarray], np.ndarray]:
    """The similarity that takes a keyframe's pose ``tracked`` to ``mapped`` and stretches every pose's offset from
    it by ``scale``: a function of a (4, 4) world_from_cam.

    Every product is pulled back onto SO(3): a chain's poses are multiplied by each correction's fix, and the next fix
    is computed from them, so rounding off SO(3) roughly doubled with every correction (1e-6 after 35 corrections in
    a row; at the end of a live KITTI stream, mapping far behind, a prediction had det R < 0)."""
    from_tracked = se3.inverse(tracked)

    def fix(pose: np.ndarray) -> np.ndarray:
        rel = from_tracked @ pose
        rel[:3, 3] *= scale
        return se3.orthonormalize(mapped @ rel)
    return fix
