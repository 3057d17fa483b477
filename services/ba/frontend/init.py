"""Two-view start: relative pose from the essential matrix of dense flow, depth by triangulation."""
from __future__ import annotations

import dataclasses
import logging
from typing import NamedTuple

import cv2
import numpy as np
import torch

from services.ba.core.params import BAParams
from services.ba.frontend import motion
from services.ba.frontend.edges import temporal_pairs
from services.ba.frontend.graph import KeyframeGraph, working_intrinsics
from services.ba.frontend.params import InitParams, MotionParams
from services.ba.frontend.rotation import bearing_rotation, translates

logger = logging.getLogger(__name__)


class TwoView(NamedTuple):
    """Second camera relative to the first and the first camera's grid disparity."""

    first_from_second: np.ndarray  # (4, 4) float64 pose of camera 2 in camera 1's frame, |t| = 1
    disparity: np.ndarray  # (h, w) float64 disparity of camera 1's grid pixels (median where unknown)
    inliers: int  # inliers of the model it came from
    model: str = "essential"  # "essential" | "homography"


def _to_working(grid_xy: np.ndarray) -> np.ndarray:
    return (grid_xy + 0.5) * 8.0 - 0.5


def _correspondences(targets: np.ndarray, confidence: np.ndarray, params: InitParams):
    h, w = confidence.shape
    if targets.shape != (h, w, 2):
        raise ValueError(f"targets ({h},{w},2) expected, got {targets.shape}")
    rows, cols = np.mgrid[0:h, 0:w]
    src = _to_working(np.stack([cols, rows], -1).reshape(-1, 2).astype(np.float64))
    dst = _to_working(targets.reshape(-1, 2).astype(np.float64))
    keep = confidence.reshape(-1) >= params.min_confidence
    return src, dst, keep


def two_view(targets: np.ndarray, confidence: np.ndarray, intrinsics_work: np.ndarray,
             params: InitParams) -> TwoView | None:
    """Relative pose of two keyframes from the grid flow ``targets`` of the first into the second (essential
    matrix).

    Args:
        targets: ``(h, w, 2)`` grid coordinates in keyframe 2 of keyframe 1's grid pixels.
        confidence: ``(h, w)`` flow confidence.
        intrinsics_work: ``(4,)`` working-resolution intrinsics (fx, fy, cx, cy).
    Returns:
        :class:`TwoView`, or None when the geometry is too weak (too few inliers or points behind).
    """
    src, dst, keep = _correspondences(targets, confidence, params)
    if keep.sum() < params.min_inliers:
        return None
    cam = _camera(intrinsics_work)
    ess, mask = cv2.findEssentialMat(src[keep], dst[keep], cam, cv2.RANSAC, 0.999, params.ransac_px)
    if ess is None or ess.shape != (3, 3):
        return None
    n_in, rot, trans, mask = cv2.recoverPose(ess, src[keep], dst[keep], cam, mask=mask)
    if n_in < params.min_inliers:
        return None
    return _with_depth(rot, trans[:, 0], src, dst, keep, mask.reshape(-1) > 0, cam, confidence.shape, params,
                       "essential")


def homography_views(targets: np.ndarray, confidence: np.ndarray, intrinsics_work: np.ndarray,
                     params: InitParams) -> tuple[list[TwoView], int]:
    """The motions a plane-induced homography allows (those that keep its points in front of both cameras;
    usually two), and the homography's inlier count. A scene that is mostly one plane (a wall, a desk) makes
    the essential matrix degenerate: it then returns either twin of the planar solution, or neither
    (TartanAir hospital, keyframes 0-4: 13 deg off, its homography twin 1.5 deg)."""
    src, dst, keep = _correspondences(targets, confidence, params)
    if keep.sum() < params.min_inliers:
        return [], 0
    hom, mask = cv2.findHomography(src[keep], dst[keep], cv2.RANSAC, params.ransac_px)
    if hom is None or mask is None or int(mask.sum()) < params.min_inliers:
        return [], 0
    inlier = mask.reshape(-1) > 0
    cam = _camera(intrinsics_work)
    n, rots, trans, normals = cv2.decomposeHomographyMat(hom, cam)
    # OpenCV's visibility test takes the points as camera rays (x, y, 1): normalised, not pixels
    before, after = (cv2.undistortPoints(p[keep][inlier].reshape(-1, 1, 2), cam, None).astype(np.float32)
                     for p in (src, dst))
    visible = cv2.filterHomographyDecompByVisibleRefpoints(rots, normals, before, after)
    views = []
    for k in ([] if visible is None else visible.reshape(-1)):
        t = trans[k][:, 0]
        if np.linalg.norm(t) < 1e-9:  # a pure rotation: no depth from this pair
            continue
        view = _with_depth(rots[k], t / np.linalg.norm(t), src, dst, keep, inlier, cam, confidence.shape, params,
                           "homography")
        if view is not None:
            views.append(view)
    return views, int(inlier.sum())


def _camera(intrinsics_work: np.ndarray) -> np.ndarray:
    fx, fy, cx, cy = intrinsics_work
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], np.float64)


def _with_depth(rot: np.ndarray, trans: np.ndarray, src, dst, keep, inlier, cam, hw, params: InitParams,
                model: str) -> TwoView | None:
    second_from_first = np.eye(4)
    second_from_first[:3, :3], second_from_first[:3, 3] = rot, trans
    depth = _triangulate(src[keep], dst[keep], cam, second_from_first)
    good = inlier & (depth > 0) & np.isfinite(depth)
    if good.sum() < params.min_inliers:
        return None
    disparity = np.full(hw[0] * hw[1], 1.0 / np.median(depth[good]))
    disparity[np.flatnonzero(keep)[good]] = 1.0 / depth[good]
    return TwoView(np.linalg.inv(second_from_first), disparity.reshape(hw), int(good.sum()), model)


def _triangulate(src: np.ndarray, dst: np.ndarray, cam: np.ndarray, second_from_first: np.ndarray) -> np.ndarray:
    """Depth in camera 1 of correspondences ``(M, 2)`` (working px); negative/inf where degenerate."""
    p1 = cam @ np.eye(4)[:3]
    p2 = cam @ second_from_first[:3]
    pts = cv2.triangulatePoints(p1, p2, src.T.copy(), dst.T.copy())
    with np.errstate(divide="ignore", invalid="ignore"):
        z1 = pts[2] / pts[3]
        z2 = (second_from_first[2, :3] @ (pts[:3] / pts[3])) + second_from_first[2, 3]
    return np.where(z2 > 0, z1, -1.0)


def start_map(graph: KeyframeGraph, params: InitParams, ba_params: BAParams, motion_params: MotionParams,
              force: bool = False) -> float | None:
    """Seed every keyframe of ``graph`` from a two-view start between its first and newest keyframe, align the
    ones between motion-only, and run a BA.

    The two-view motion has candidates: the essential matrix's, and the homography's (a mostly planar scene
    leaves the essential matrix degenerate). Each seeds the window and is adjusted; the lowest BA cost wins.
    Two keyframes of a plane cannot tell a homography's twin motions apart, so a planar start waits for a third.

    Returns the final BA cost (inf when forced without a two-view solution: identity poses), or None (graph
    unchanged) when there is not yet enough parallax; ``force`` tries with what there is.
    """
    n = len(graph)
    if n < 2 or (n < params.min_keyframes and not force):
        return None
    flow = parallax(graph)
    if (flow < params.min_flow or translation(graph, params) is False) and not force:
        return None
    tg = graph.targets(0, n - 1)
    candidates = _candidates(tg, working_intrinsics(graph.intrinsics), params, n, force)
    if candidates is None:  # planar with two keyframes: wait for a third
        return None
    if not candidates:
        if not force:
            return None
        logger.debug("forced two-view start: no candidate motion")
        return float("inf")
    iterations = dataclasses.replace(ba_params, iterations=params.iterations)
    best, costs = candidates[0], []
    if len(candidates) > 1:
        adjusted = []  # each candidate's cost and adjusted map: the winner's is kept, not computed again
        for c in candidates:
            adjusted.append((_seed_and_adjust(graph, c, iterations, motion_params), graph.snapshot()))
        costs = [c for c, _ in adjusted]
        pick = int(np.argmin(costs))
        best, (cost, state) = candidates[pick], adjusted[pick]
        graph.restore(state)
    else:
        cost = _seed_and_adjust(graph, best, iterations, motion_params)
    logger.info("map initialised", extra={"keyframes": n, "inliers": best.inliers, "model": best.model,
                                          "flow": round(flow, 2), "candidate_costs": [round(c, 3) for c in costs]})
    return cost


def _candidates(tg, intrinsics_work: np.ndarray, params: InitParams, n: int, force: bool) -> list[TwoView] | None:
    """Two-view motions to try: the essential matrix's and the homography's; None when the scene is planar and
    two keyframes cannot tell the homography's twin motions apart (wait for a third)."""
    args = (tg.target.numpy(), tg.confidence.numpy(), intrinsics_work, params)
    essential = two_view(*args)
    planar, h_inliers = homography_views(*args)
    e_inliers = essential.inliers if essential is not None else 0
    if n < 3 and len(planar) > 1 and h_inliers >= params.planar_ratio * e_inliers and not force:
        return None
    return ([essential] if essential is not None else []) + planar


def _seed_and_adjust(graph: KeyframeGraph, start: TwoView, ba_params: BAParams, motion_params: MotionParams) -> float:
    """Every keyframe's pose and disparity from ``start``, then a BA over them; the final BA cost (inf when the
    BA failed). Overwrites the graph's poses and disparities."""
    n, first, last = len(graph), 0, len(graph) - 1
    dev, dtype = graph.device, torch.float64
    disp = torch.from_numpy(start.disparity).to(dev, dtype)
    prior = graph.priors[first]
    if prior is not None and ba_params.alpha_disp > 0 and bool((prior > 0).any()):
        scale = float(prior[prior > 0].median()) / float(disp[prior.to(dev) > 0].median())
        disp = disp * scale
        start = start._replace(first_from_second=_scaled(start.first_from_second, 1.0 / scale, rotate=False))
    graph.poses[first] = torch.eye(4, dtype=dtype, device=dev)
    graph.disparity[first] = disp
    graph.poses[last] = torch.from_numpy(start.first_from_second).to(dev, dtype)
    median = torch.full_like(disp, float(disp.median()))
    for k in range(1, n):
        graph.disparity[k] = median.clone()
        if k == last:
            continue
        t = graph.targets(first, k)
        frac = k / last
        init = torch.from_numpy(_scaled(start.first_from_second, frac)).to(dev, dtype)
        res = motion.align(init, graph.poses[first][None], disp[None], t.target[None].to(dev),
                           t.confidence[None].to(dev), graph.intrinsics, motion_params)
        graph.poses[k] = torch.from_numpy(res.pose).to(init) if res.ok else init
    everything = list(range(n))
    result = graph.run(everything, temporal_pairs(everything, 2), ba_params)
    return float("inf") if result is None else float(result.costs[-1])


def calibrate_focal(graph: KeyframeGraph, params: InitParams, ba_params: BAParams, motion_params: MotionParams,
                    ratios: tuple[float, ...], only_undetermined: bool = False) -> float | None:
    """Start the map again from ``ratios`` x the focal guess (``ba_params`` with the focal free) and keep the
    lowest BA cost, the map as it is (adjusted the same way) included. Returns the winning ratio, or None when the
    map as it was won. Two keyframes cannot tell focal lengths apart, six with rotation can; and incremental BA
    started far above the true focal runs further away (hand-held desk, 83 deg camera from the 60 deg guess: to the
    upper bound; restarted: 429 px, true 420.5). A start whose focal ends at a bound is not one the data
    determined (forward motion: KITTI's restarts fall to the lower bound at a lower cost) and is not taken.
    ``only_undetermined``: the restarts run only when the map as it is ends at a bound (a live camera's mapping
    cannot stall for them where its own BA found a focal)."""
    everything = list(range(len(graph)))
    result = graph.run(everything, temporal_pairs(everything, 2), ba_params)
    best = (float("inf") if result is None else float(result.costs[-1]), None, graph.snapshot())
    as_is = [p.clone() for p in graph.poses]
    aspect = float(graph.intrinsics[1] / graph.intrinsics[0])
    low, high = (r * graph.first_focal for r in graph.focal_range)
    determined = result is not None and low * 1.02 < float(graph.intrinsics[0]) < high / 1.02
    for ratio in () if only_undetermined and determined else ratios:
        graph.intrinsics = graph.intrinsics.clone()
        graph.intrinsics[0], graph.intrinsics[1] = graph.first_focal * ratio, graph.first_focal * ratio * aspect
        graph.intrinsics[2:] = graph.intrinsics.new_tensor(graph.first_principal)  # each restart from the guess
        cost = start_map(graph, params, ba_params, motion_params, force=True)
        focal = float(graph.intrinsics[0])
        if cost is not None and cost < best[0] and low * 1.02 < focal < high / 1.02:
            best = (cost, ratio, graph.snapshot())
    graph.restore(best[2])
    if best[1] is not None:
        _keep_scale(graph, as_is)
    logger.info("focal calibrated", extra={"keyframes": len(graph), "cost": best[0], "restart": best[1],
                                           "focal_grid": round(float(graph.intrinsics[0]), 3)})
    return best[1]


def _keep_scale(graph: KeyframeGraph, before: list[torch.Tensor]) -> None:
    """A restarted map in the scale of the map it replaces (both start at the identity): the least-squares scale
    between their camera centres, applied to translations and disparities. Poses already published, tracking's
    relative poses and its carried-over depth stay in the same world frame instead of jumping by the restart's
    arbitrary scale."""
    new = torch.stack([p[:3, 3] for p in graph.poses])
    old = torch.stack([p[:3, 3] for p in before]).to(new)
    norm = float((new * new).sum())
    if norm <= 0:
        return
    scale = float((old * new).sum()) / norm
    if not scale > 0:
        return
    for k in range(len(graph)):
        pose = graph.poses[k].clone()
        pose[:3, 3] *= scale
        graph.poses[k] = pose
        graph.disparity[k] = graph.disparity[k] / scale


def parallax(graph: KeyframeGraph) -> float:
    """Mean grid flow (grid px) between the first and the newest keyframe."""
    return _mean_grid_flow(graph.targets(0, len(graph) - 1).target.numpy())


def translation(graph: KeyframeGraph, params: InitParams) -> bool | None:
    """Whether the flow between the first and the newest keyframe shows translation, not only rotation
    (:func:`rotation.translates`); None where the flow broke too far to tell."""
    t = graph.targets(0, len(graph) - 1)
    return translates(t.target.numpy(), t.confidence.numpy(), graph.intrinsics.cpu().numpy(), 1,
                      graph.flow_params.fb_sigma / graph.flow_params.grid, params.min_parallax_ratio,
                      params.min_confidence)


def turning(graph: KeyframeGraph, params: InitParams) -> bool:
    """The keyframes so far only turn on the spot: three or more, the first and newest far apart in the image
    (``min_flow``) and no translation between them. Waiting for parallax would outlast the flow (beyond ~12 grid
    px DIS loses a turn and its broken flow reads as parallax); the map starts as a rotation instead."""
    return len(graph) >= 3 and parallax(graph) >= params.min_flow and translation(graph, params) is False


def start_static(graph: KeyframeGraph) -> None:
    """No parallax for a two-view start (a fixed camera watching people, a camera turning on the spot): every
    keyframe keeps the first keyframe's position, turned by the rotations that explain the flow between each
    keyframe and the one before (chained), with a constant disparity; frames are still aligned to them, so a camera
    that did move a little gets that motion, and one that did not stays put."""
    dev, dtype = graph.device, torch.float64
    graph.poses[0] = torch.eye(4, dtype=dtype, device=dev)
    for k in range(len(graph)):
        graph.disparity[k] = torch.ones(graph.grid_hw, dtype=dtype, device=dev)
        if k:
            t = graph.targets(k - 1, k)
            turn = bearing_rotation(t.target.numpy(), t.confidence.numpy(), graph.intrinsics.cpu().numpy(), 1)
            pose = graph.poses[k - 1].clone()
            pose[:3, :3] = pose[:3, :3] @ torch.from_numpy(turn.T).to(dev, dtype)  # world_from_k = world_from_k-1 @ k-1_from_k
            graph.poses[k] = pose
    logger.info("no parallax: keyframes keep the first position, turned as their flow says",
                extra={"keyframes": len(graph)})


def _mean_grid_flow(targets: np.ndarray) -> float:
    h, w = targets.shape[:2]
    rows, cols = np.mgrid[0:h, 0:w]
    return float(np.linalg.norm(targets - np.stack([cols, rows], -1), axis=-1).mean())


def _scaled(pose: np.ndarray, frac: float, rotate: bool = True) -> np.ndarray:
    """Translation scaled by ``frac``; with ``rotate`` the rotation angle too (a point along the motion)."""
    out = np.eye(4)
    rvec, _ = cv2.Rodrigues(pose[:3, :3])
    out[:3, :3] = cv2.Rodrigues(rvec * frac)[0] if rotate else pose[:3, :3]
    out[:3, 3] = pose[:3, 3] * frac
    return out
