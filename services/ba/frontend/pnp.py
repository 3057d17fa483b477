"""Relocalisation: a camera's pose against a mapped keyframe from image features alone, with no motion prior.

After a lost view (a covered lens, a whip pan, a dropped stretch of frames) the motion since the last good frame is
unknown. A constant-velocity prediction is then a guess, and DIS flow started from the flow that guess induces
settles on whatever minimum is nearest: on the synthetic orbit with 20 frames blanked, the keyframe after the gap
joined the map 17 deg off its true turn and the map after the gap was a second map, 0.23 m from the first.
As ORB-SLAM relocalises against its map points, ORB features of the keyframe, lifted to 3D by its BA depth, are
matched into the image and PnP RANSAC gives a pose in the map's frame and scale. The pose is one more start for
the flow and the motion-only alignment; the caller keeps whichever start's alignment the flow supports most
(:func:`services.ba.frontend.relocalise.realign_keyframe` for keyframes, the tracker for frames).

numpy and OpenCV only: the tracking process imports it without torch.
"""
from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np

from services.ba.core.host_arrays import as_numpy
from services.ba.core.params import GRID
from services.ba.frontend.params import RelocaliseParams
from services.common.camera import scale_intrinsics


class Relocalised(NamedTuple):
    pose: np.ndarray  # (4, 4) float64 world_from_cam of the camera
    inliers: int  # PnP RANSAC inliers
    matches: int  # matches that passed the ratio test and had depth


class Features(NamedTuple):
    """ORB keypoints of one image."""

    points: np.ndarray  # (N, 2) float64 keypoint positions, working pixels
    descriptors: np.ndarray | None  # (N, 32) uint8; None when none were found


def orb_features(image: np.ndarray, params: RelocaliseParams = RelocaliseParams(), scale: int = 1) -> Features:
    """ORB keypoints of ``image`` ((H, W) uint8 grey at 1/``scale`` of the working size), in working pixels."""
    if scale != 1:  # ORB at a quarter of the pixels finds too few keypoints away from its border (half-size
        # frames 31 frames from their keyframe: 33 inliers, none at 35); at the working size again it finds 50+
        image = cv2.resize(image, (image.shape[1] * scale, image.shape[0] * scale), interpolation=cv2.INTER_LINEAR)
    keypoints, descriptors = cv2.ORB_create(nfeatures=params.features).detectAndCompute(image, None)
    return Features(np.float64([k.pt for k in keypoints]).reshape(-1, 2), descriptors)


def pnp_pose(ref_image: np.ndarray, ref_pose, ref_disparity, grid_k,
             image: np.ndarray, params: RelocaliseParams = RelocaliseParams(), scale: int = 1) -> Relocalised | None:
    """World_from_cam of the camera that took ``image`` from keyframe ``ref_image`` (both ``(H, W)`` uint8 grey at
    1/``scale`` of the working size), its ``ref_pose`` ((4, 4) world_from_cam) and ``ref_disparity`` ((h, w) grid
    disparity, 1 / depth; 0 where unknown), with ``grid_k`` the (4,) grid intrinsics both share (numpy arrays or
    torch tensors). None when too few matches agree."""
    return pose_from_features(orb_features(ref_image, params, scale), ref_pose, ref_disparity, grid_k,
                              orb_features(image, params, scale), params)


def pose_from_features(ref: Features, ref_pose, ref_disparity, grid_k,
                       cam: Features, params: RelocaliseParams = RelocaliseParams()) -> Relocalised | None:
    """:func:`pnp_pose` from the ORB features of both images (a tracker keeps its reference's)."""
    if ref.descriptors is None or cam.descriptors is None or len(ref.points) < params.min_inliers or len(cam.points) < 2:
        return None
    pairs = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(ref.descriptors, cam.descriptors, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < params.ratio * p[1].distance]
    if len(good) < params.min_inliers:
        return None
    uv_ref = ref.points[[m.queryIdx for m in good]]
    uv_cam = cam.points[[m.trainIdx for m in good]]
    k_work = _working_k(grid_k)
    disparity = _sample(as_numpy(ref_disparity), (uv_ref - (GRID - 1) / 2) / GRID)
    keep = disparity > 1e-6
    if int(keep.sum()) < params.min_inliers:
        return None
    uv_ref, uv_cam, disparity = uv_ref[keep], uv_cam[keep], disparity[keep]
    rays = np.column_stack([(uv_ref[:, 0] - k_work[0, 2]) / k_work[0, 0], (uv_ref[:, 1] - k_work[1, 2]) / k_work[1, 1],
                            np.ones(len(uv_ref))])
    points_ref = rays / disparity[:, None]  # in the keyframe's camera
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(points_ref, uv_cam, k_work, None, iterationsCount=params.iterations,
                                                 reprojectionError=params.reprojection_px, confidence=0.999,
                                                 flags=cv2.SOLVEPNP_EPNP)
    if not ok or inliers is None or len(inliers) < params.min_inliers:
        return None
    idx = inliers[:, 0]
    rvec, tvec = cv2.solvePnPRefineLM(points_ref[idx], uv_cam[idx], k_work, None, rvec, tvec)
    cam_from_ref = np.eye(4)
    cam_from_ref[:3, :3] = cv2.Rodrigues(rvec)[0]
    cam_from_ref[:3, 3] = tvec[:, 0]
    world_from_cam = as_numpy(ref_pose) @ np.linalg.inv(cam_from_ref)
    if not bool(np.isfinite(world_from_cam).all()):
        return None
    return Relocalised(world_from_cam, len(idx), len(uv_ref))


def _working_k(grid_k) -> np.ndarray:
    """Camera matrix at the working size from the (4,) grid intrinsics."""
    fx, fy, cx, cy = scale_intrinsics(as_numpy(grid_k), GRID, GRID)
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _sample(grid: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``grid`` (h, w) at grid coordinates ``xy`` (N, 2); 0 outside and where any of the four
    cells is 0 (no depth there: a blend with it would be a point that is not in the scene)."""
    h, w = grid.shape
    x, y = xy[:, 0], xy[:, 1]
    inside = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    x0 = np.clip(np.floor(x).astype(int), 0, w - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, h - 2)
    fx, fy = np.clip(x - x0, 0, 1), np.clip(y - y0, 0, 1)
    value = (grid[y0, x0] * (1 - fx) * (1 - fy) + grid[y0, x0 + 1] * fx * (1 - fy)
             + grid[y0 + 1, x0] * (1 - fx) * fy + grid[y0 + 1, x0 + 1] * fx * fy)
    corners = np.stack([grid[y0, x0], grid[y0, x0 + 1], grid[y0 + 1, x0], grid[y0 + 1, x0 + 1]])
    return np.where(inside & (corners > 0).all(axis=0), value, 0.0)
