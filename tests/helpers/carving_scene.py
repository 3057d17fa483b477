"""A carving test scene with exact geometry: rectangles parallel to a wall, depth maps ray-cast on the 1/8 grid.

World: a wall in the plane z = 5 (facing the cameras, which look along +z), optional boxes (their front
faces, rectangles at a given z) in front of it. A keyframe's points are back-projected from its exact depth.
Labelled variants give each cell the code of its label (near-orthogonal unit vectors plus noise, as oracle
features are) for the semantic evidence.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from services.mapstore.core.carving import CarveView, unit_codes
from services.mapstore.core.geometry import backproject_grid, grid_intrinsics, transform_points
from services.mapstore.core.keyframe import KeyframeContent, KeyframeDepth
from services.mapstore.core.map import KeyframeMap

H, W = 12, 16  # 1/8 grid of a 96x128 working image
INTR = np.array([100.0, 100.0, 63.5, 47.5])
WALL_Z = 5.0


class Rect(NamedTuple):
    """A rectangle facing the cameras: x in [x0, x1], y in [y0, y1] at world depth z."""

    x0: float
    x1: float
    y0: float
    y1: float
    z: float


BOX = Rect(-0.6, 0.6, -0.5, 0.5, 3.0)
MOVED_BOX = Rect(1.4, 2.4, -0.5, 0.5, 3.0)
OCCLUDER = Rect(-1.5, 1.5, -1.2, 1.2, 1.5)


def cam_pose(tx: float) -> np.ndarray:
    pose = np.eye(4)
    pose[0, 3] = tx
    return pose


def render_disparity(world_from_cam: np.ndarray, rects: list[Rect]) -> np.ndarray:
    """(H, W) float32 exact disparity of the wall and the nearest rectangle hit by each cell's centre ray."""
    return render(world_from_cam, rects)[0]


def render(world_from_cam: np.ndarray, rects: list[Rect]) -> tuple[np.ndarray, np.ndarray]:
    """((H, W) float32 exact disparity, (H, W) int64 index of the rectangle each cell sees, −1 = the wall)."""
    gk = grid_intrinsics(INTR)
    v, u = np.meshgrid(np.arange(H, dtype=np.float64), np.arange(W, dtype=np.float64), indexing="ij")
    rays = np.stack([(u - gk[2]) / gk[0], (v - gk[3]) / gk[1], np.ones_like(u)], -1) @ world_from_cam[:3, :3].T
    origin = world_from_cam[:3, 3]
    depth = (WALL_Z - origin[2]) / rays[..., 2]  # camera z of the hit = ray parameter (camera-frame ray has z = 1)
    which = np.full(depth.shape, -1, np.int64)
    for i, r in enumerate(rects):
        s = (r.z - origin[2]) / rays[..., 2]
        x, y = origin[0] + s * rays[..., 0], origin[1] + s * rays[..., 1]
        hit = (x >= r.x0) & (x <= r.x1) & (y >= r.y0) & (y <= r.y1) & (s > 0) & (s < depth)
        depth = np.where(hit, s, depth)
        which = np.where(hit, i, which)
    return (1.0 / depth).astype(np.float32), which


def view(tx: float, rects: list[Rect], reliability: np.ndarray | None = None) -> CarveView:
    pose = cam_pose(tx)
    return CarveView(np.linalg.inv(pose), render_disparity(pose, rects), INTR, reliability)


def points_of(tx: float, rects: list[Rect]) -> tuple[np.ndarray, np.ndarray]:
    """World points (H·W, 3) of a keyframe at x = tx and whether each lies on a rectangle (not the wall)."""
    pose = cam_pose(tx)
    pts = backproject_grid(render_disparity(pose, rects), grid_intrinsics(INTR)).reshape(-1, 3)
    world = transform_points(pose, pts)
    return world, world[:, 2] < WALL_Z - 1e-6


def near_rect(xyz: np.ndarray, r: Rect, tol: float = 0.05) -> np.ndarray:
    return ((np.abs(xyz[:, 2] - r.z) < tol) & (xyz[:, 0] > r.x0 - tol) & (xyz[:, 0] < r.x1 + tol)
            & (xyz[:, 1] > r.y0 - tol) & (xyz[:, 1] < r.y1 + tol))


def add_keyframe(m: KeyframeMap, kf: int, pose: np.ndarray, disparity: np.ndarray, codes: np.ndarray,
                 version: int = 1) -> None:
    """Give ``m`` keyframe ``kf`` (content with ``codes`` of PCA ``version``, exact depth, pose); no refresh."""
    m.add_content(KeyframeContent(kf, kf * 1000, codes, np.zeros((H, W, 3), np.uint8), (8 * H, 8 * W), version))
    m.set_depth(kf, KeyframeDepth(disparity, INTR))
    m.set_pose(kf, pose)


WALL, CHAIR, FLOOR, PERSON = 0, 1, 2, 3
LABEL_CODES = np.linalg.qr(np.random.default_rng(7).normal(size=(8, 4)))[0].T  # (4 labels, K = 8) orthonormal


def label_codes(labels: np.ndarray, noise: float = 0.1, seed: int = 0) -> np.ndarray:
    """(…, K) float16 codes of an (…) label map: each label's unit vector plus Gaussian noise of relative size
    `noise`."""
    rng = np.random.default_rng(seed)
    codes = LABEL_CODES[labels] + noise / np.sqrt(LABEL_CODES.shape[1]) * rng.normal(size=(*labels.shape, 8))
    return codes.astype(np.float16)


def cell_labels(which: np.ndarray, rect_labels: list[int]) -> np.ndarray:
    """(H, W) labels of a render's rectangle indices (−1 = the wall)."""
    return np.where(which < 0, WALL, np.asarray(rect_labels + [WALL])[which])


def labelled_view(tx: float, rects: list[Rect], rect_labels: list[int], reliability: np.ndarray | None = None,
                  seed: int = 1) -> CarveView:
    pose = cam_pose(tx)
    disparity, which = render(pose, rects)
    codes = unit_codes(label_codes(cell_labels(which, rect_labels), seed=seed))
    return CarveView(np.linalg.inv(pose), disparity, INTR, reliability, codes)


def labelled_points(tx: float, rects: list[Rect], rect_labels: list[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(world points (H·W, 3), their codes (H·W, K), whether each lies on a rectangle) of a keyframe at x = tx."""
    pts, on_rect = points_of(tx, rects)
    _, which = render(cam_pose(tx), rects)
    return pts, label_codes(cell_labels(which, rect_labels).reshape(-1)), on_rect


# Where the chair stood, later monocular depth puts the floor at 0.85× the chair's depth (pulled towards it): a
# floor-labelled surface in front of the old chair points, wider than the chair, that no depth test sees through.
PULLED_FLOOR = Rect(BOX.x0 - 0.3, BOX.x1 + 0.3, BOX.y0 - 0.3, BOX.y1 + 0.3, 0.85 * BOX.z)
