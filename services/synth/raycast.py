"""Vectorised ray casting against the room (an inside-out box) and axis-aligned boxes.

Rays are given per pixel as world directions ``d`` (3, H, W) planes whose camera-frame z component is 1, so the
ray parameter t of a hit *is* its depth (z in the camera frame). Faces are numbered ``2 * axis + side``
with side 0 the box's min plane along that axis and side 1 its max plane.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

TINY_DIRECTION = 1e-9  # replaces exact zeros in ray directions so 1/d stays finite
REGION_MARGIN_PX = 1  # pixels added around a box's projected bounding rectangle


@dataclass
class Hits:
    """Nearest hit per pixel so far (updated in place by :func:`cast_box`)."""

    depth: np.ndarray  # (H, W) float32 ray parameter = camera z, metres
    box: np.ndarray  # (H, W) int32: 0 = room, k + 1 = box k
    face: np.ndarray  # (H, W) int8: 2 * axis + side


def safe_inverse(d: np.ndarray) -> np.ndarray:
    """1 / d elementwise (float32) with zeros nudged to ±TINY_DIRECTION."""
    d = np.where(d == 0, np.float32(TINY_DIRECTION), d)
    return (1.0 / d).astype(np.float32)


def cast_room(origin: np.ndarray, d: np.ndarray, inv: np.ndarray, room_hi: np.ndarray) -> Hits:
    """Exit point of every ray from the room [0, room_hi] (the origin must lie inside the room).

    origin: (3,) world; d, inv: (3, H, W) float32 direction planes and their inverses; room_hi: (3,) metres.
    """
    t = [np.where(d[k] > 0, np.float32(room_hi[k] - origin[k]), np.float32(-origin[k])) * inv[k] for k in range(3)]
    axis = np.where(t[0] <= np.minimum(t[1], t[2]), 0, np.where(t[1] <= t[2], 1, 2))
    depth = np.minimum(np.minimum(t[0], t[1]), t[2])
    ahead = np.choose(axis, d) > 0  # leaving through the max plane of that axis
    face = (2 * axis + ahead).astype(np.int8)
    return Hits(depth.astype(np.float32), np.zeros(depth.shape, np.int32), face)


def screen_region(lo: np.ndarray, hi: np.ndarray, cam_from_world: np.ndarray, intr: np.ndarray,
                  shape: tuple[int, int], near: float) -> tuple[slice, slice] | None:
    """Pixel rectangle (rows, cols) that can see the box [lo, hi] (world, (3,) each); None if none can.

    Conservative: the bounding rectangle of the 8 projected corners, or the whole image when the box
    straddles the camera plane.
    """
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    pc = corners @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    h, w = shape
    if (pc[:, 2] <= near).all():
        return None
    if (pc[:, 2] <= near).any():
        return slice(0, h), slice(0, w)
    fx, fy, cx, cy = intr
    u = fx * pc[:, 0] / pc[:, 2] + cx
    v = fy * pc[:, 1] / pc[:, 2] + cy
    c0 = int(max(np.floor(u.min()) - REGION_MARGIN_PX, 0))
    c1 = int(min(np.ceil(u.max()) + REGION_MARGIN_PX + 1, w))
    r0 = int(max(np.floor(v.min()) - REGION_MARGIN_PX, 0))
    r1 = int(min(np.ceil(v.max()) + REGION_MARGIN_PX + 1, h))
    if c0 >= c1 or r0 >= r1:
        return None
    return slice(r0, r1), slice(c0, c1)


def cast_box(hits: Hits, origin: np.ndarray, d: np.ndarray, inv: np.ndarray, lo: np.ndarray, hi: np.ndarray,
             region: tuple[slice, slice], index: int, near: float) -> None:
    """Slab test of box [lo, hi] (world (3,) each) for the pixels in ``region``; keeps the nearer hit.

    d, inv: (3, H, W) float32 direction planes and their inverses. Writes ``index`` into ``hits.box`` where
    this box is the nearest surface found so far.
    """
    t_in, t_out = [], []
    for k in range(3):
        ik = inv[k][region]
        ta, tb = np.float32(lo[k] - origin[k]) * ik, np.float32(hi[k] - origin[k]) * ik
        t_in.append(np.minimum(ta, tb))
        t_out.append(np.maximum(ta, tb))
    t_near = np.maximum(np.maximum(t_in[0], t_in[1]), t_in[2])
    t_far = np.minimum(np.minimum(t_out[0], t_out[1]), t_out[2])
    depth = hits.depth[region]
    hit = (t_near <= t_far) & (t_near > near) & (t_near < depth)
    if not hit.any():
        return
    tn = t_near[hit]
    axis = np.where(t_in[0][hit] == tn, 0, np.where(t_in[1][hit] == tn, 1, 2))  # the slab entered last
    d_axis = np.where(axis == 0, d[0][region][hit], np.where(axis == 1, d[1][region][hit], d[2][region][hit]))
    depth[hit] = tn
    hits.box[region][hit] = index
    hits.face[region][hit] = (2 * axis + (d_axis < 0)).astype(np.int8)  # going -axis: enters the max plane
