"""Edges of the keyframe graph: temporal pairs, proximity by induced flow with non-maximum suppression."""
from __future__ import annotations

from typing import NamedTuple

import torch

from services.ba.core import projective
from services.ba.frontend.params import GraphParams


def induced_flow(poses: torch.Tensor, disparity: torch.Tensor, intrinsics: torch.Tensor, ii: torch.Tensor,
                 jj: torch.Tensor) -> torch.Tensor:
    """Mean displacement (grid px) of keyframe ``ii``'s grid pixels reprojected into keyframe ``jj``.

    Args:
        poses: ``(N, 4, 4)`` world_from_cam; disparity: ``(N, h, w)``; intrinsics: ``(4,)`` grid intrinsics.
        ii, jj: ``(E,)`` long keyframe indices.
    Returns:
        ``(E,)`` mean flow over pixels in front of camera ``jj`` (``inf`` where none is).
    """
    n, h, w = disparity.shape
    if ii.numel() == 0:
        return torch.zeros(0, dtype=poses.dtype, device=poses.device)
    pixels = projective.pixel_grid(h, w, poses.dtype, poses.device)
    rp = projective.reproject(poses[ii], poses[jj], disparity.reshape(n, -1)[ii].to(poses.dtype), pixels,
                              intrinsics, with_jacobians=False)
    valid = rp.valid.to(poses.dtype)
    dist = (_length(rp.coords - pixels) * valid).sum(-1) / valid.sum(-1).clamp_min(1)
    return torch.where(valid.sum(-1) > 0, dist, torch.full_like(dist, float("inf")))


def _length(flow: torch.Tensor) -> torch.Tensor:
    """``(..., 2)`` vectors' lengths. ``reproject`` lays its coordinates out as x and y planes, and ``norm`` over
    that strided last dimension took 33 ms for 63 edges of a KITTI grid, where ``hypot`` of the planes takes 0.2 ms."""
    return torch.hypot(flow[..., 0], flow[..., 1])


class FlowParts(NamedTuple):
    """The induced flow of keyframe pairs taken apart (grid px means over the pixels in front of the target)."""

    induced: torch.Tensor  # (E,) the whole induced flow (:func:`induced_flow`, from the same reprojection)
    parallax: torch.Tensor  # (E,) the flow the source's depth causes: reprojection minus the rotation's alone
    rotation: torch.Tensor  # (E,) the flow the rotation alone causes (the points at infinity)
    overlap: torch.Tensor  # (E,) share of the source's pixels that land inside the target image


def flow_parts(poses: torch.Tensor, disparity: torch.Tensor, intrinsics: torch.Tensor, ii: torch.Tensor,
               jj: torch.Tensor) -> FlowParts:
    """:func:`induced_flow`'s pairs, their flow split into parallax and rotation (arguments as there)."""
    n, h, w = disparity.shape
    pixels = projective.pixel_grid(h, w, poses.dtype, poses.device)
    disp = disparity.reshape(n, -1)[ii].to(poses.dtype)
    at = projective.reproject(poses[ii], poses[jj], disp, pixels, intrinsics, with_jacobians=False)
    far = projective.reproject(poses[ii], poses[jj], torch.zeros_like(disp), pixels, intrinsics,
                               with_jacobians=False)
    valid = (at.valid & far.valid).to(poses.dtype)
    x, y = at.coords[..., 0], at.coords[..., 1]
    inside = valid * ((x >= -0.5) & (x <= w - 0.5) & (y >= -0.5) & (y <= h - 0.5)).to(poses.dtype)

    def mean(flow: torch.Tensor) -> torch.Tensor:
        return torch.nan_to_num(_length(flow) * valid).sum(-1) / valid.sum(-1).clamp_min(1)

    return FlowParts(mean(at.coords - pixels), mean(at.coords - far.coords), mean(far.coords - pixels),
                     inside.sum(-1) / (h * w))


def temporal_pairs(indices: list[int], radius: int) -> list[tuple[int, int]]:
    """Directed pairs ``(a, b)`` of ``indices`` (sorted keyframe ids) at most ``radius`` apart in the list."""
    pairs = []
    for pos, a in enumerate(indices):
        for b in indices[max(0, pos - radius): pos]:
            pairs += [(a, b), (b, a)]
    return pairs


def proximity_pairs(new: int, candidates: list[int], flow: torch.Tensor, params: GraphParams) -> list[tuple[int, int]]:
    """Proximity edges of keyframe ``new``: the candidates with the least induced flow below
    ``params.proximity_max_flow``, greedily, each suppressing candidates within ``params.proximity_nms``
    keyframe indices of it (non-maximum suppression); both directions.

    Args:
        candidates: keyframe ids (not temporal neighbours of ``new``); flow: ``(len(candidates),)`` grid px.
    """
    if len(candidates) != flow.numel():
        raise ValueError(f"{len(candidates)} candidates but {flow.numel()} flow values")
    chosen: list[int] = []
    for k in torch.argsort(flow).tolist():
        if float(flow[k]) >= params.proximity_max_flow or len(chosen) >= params.proximity_max_edges:
            break
        if all(abs(candidates[k] - c) > params.proximity_nms for c in chosen):
            chosen.append(candidates[k])
    return [p for c in chosen for p in ((new, c), (c, new))]
