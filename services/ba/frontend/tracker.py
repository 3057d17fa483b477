"""Frame-rate tracking: every frame's pose at once, motion-only against the newest mapped keyframe.

Mapping (window BA) runs per keyframe and takes hundreds of milliseconds; a frame cannot wait for it. The
tracker holds a snapshot of one reference keyframe — its pose, grid disparity and image, as the last BA left
them — and aligns each frame to it: DIS flow from the reference into the frame (at the size frames arrive in),
started from the flow a constant-velocity prediction induces, then the 6-dof Gauss-Newton of
:mod:`services.ba.frontend.motion`. Mapping later revises the pose against the keyframes that bracket the
frame (:mod:`services.ba.frontend.frames`). As in DSO's coarse tracker, the reference only changes when the
mapper hands over a newer keyframe, so tracking never reads state that mapping is changing.

When mapping falls behind (a live camera on a shared CPU), waiting for its next keyframe would leave tracking
aligned to a keyframe ever further back until the flow breaks. So while mapping does not hold the keyframe
before the newest, a keyframe that tracking itself aligned is promoted to reference, its depth the reference's
grid disparity carried over by the tracked motion (:func:`propagate_disparity`, as SVO and LSD-SLAM carry depth
to a new keyframe); mapping's result replaces it once mapping is at most one keyframe behind.
"""
from __future__ import annotations

from dataclasses import replace
from typing import NamedTuple

import cv2
import numpy as np
import torch

from services.ba.core import flow as core_flow
from services.ba.core import se3
from services.ba.core.params import FlowParams
from services.ba.frontend import motion
from services.ba.frontend.edges import induced_flow_field
from services.ba.frontend.params import MotionParams

GRID = 8  # working pixels per grid cell (docs/CONVENTIONS.md)


class Reference(NamedTuple):
    """A mapped keyframe the tracker aligns frames to (a snapshot: the mapper never changes it in place)."""

    seq: int
    stamp: int  # t_ns
    pose: torch.Tensor  # (4, 4) float64 world_from_cam
    disparity: torch.Tensor  # (h, w) float64 grid disparity
    intrinsics: torch.Tensor  # (4,) float64 grid intrinsics
    image: np.ndarray  # (H, W) uint8 grey at working resolution
    previous: tuple[int, torch.Tensor] | None = None  # (t_ns, world_from_cam) of the keyframe before: its motion
    known: torch.Tensor | None = None  # (h, w) 1 where the disparity is measured, 0 where it was only filled in


class Tracked(NamedTuple):
    seq: int
    stamp: int
    pose: torch.Tensor  # (4, 4) float64 world_from_cam
    ref_seq: int  # the keyframe it was aligned to
    ok: bool  # False: too little flow to align; the pose is the constant-velocity prediction


MAX_EXTRAPOLATION = 8.0  # a prediction extends a motion at most this many times its own duration


def _extrapolate(t0: int, pose0: torch.Tensor, t1: int, pose1: torch.Tensor, stamp: int) -> torch.Tensor:
    """The motion from (t0, pose0) to (t1, pose1) continued at the same rate to ``stamp`` (geodesic in SE3)."""
    span = t1 - t0
    frac = (stamp - t1) / span if span > 0 else 0.0
    rel = se3.inverse(pose0) @ pose1
    return se3.orthonormalize(pose1 @ se3.exp(min(frac, MAX_EXTRAPOLATION) * se3.log(rel)))


# A tracked pose is trusted (anchors the frame, promotes a keyframe) only with this much evidence: at least this
# share of the reference's grid cells left after the robust weights, and a weighted RMS flow residual below this
# (grid px). On the synthetic world a frame 14 frames from its reference still has 4 % and 0.57 px; 30 frames away
# 3 % and 1.2 px, a pose one should not build on.
TRACK_MIN_SHARE = 0.03
TRACK_MAX_RMS = 1.0
PHOTO_SIGMA = 0.5  # photometric disagreement (in image standard deviations) where confidence falls to exp(-1/2)


def photometric_agreement(ref: np.ndarray, image: np.ndarray, target: np.ndarray, grid: int) -> np.ndarray:
    """(h, w) weight in [0, 1]: how well the frame's intensity where each reference cell lands matches the cell.

    Forward-backward consistency alone accepts any smooth flow, also the one DIS returns on a blank or
    overexposed frame; brightness (each image normalised by its own mean and deviation, so exposure changes do
    not count) is the evidence that the cell really is there. A frame with no contrast gets weight 0.
    """
    h, w = target.shape[:2]
    ref_cells = cv2.resize(ref, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32)
    blurred = cv2.blur(image, (grid, grid)).astype(np.float32)
    px = (target + 0.5) * grid - 0.5  # grid coordinates -> pixels of these images (docs/CONVENTIONS.md)
    landed = cv2.remap(blurred, px[..., 0].astype(np.float32), px[..., 1].astype(np.float32), cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_REPLICATE)
    spread = float(blurred.std())
    if spread < 1.0:
        return np.zeros((h, w), np.float32)
    diff = (ref_cells - ref_cells.mean()) / max(float(ref_cells.std()), 1.0) - (landed - blurred.mean()) / spread
    return np.exp(-0.5 * (diff / PHOTO_SIGMA) ** 2).astype(np.float32)


def propagate_disparity(pose_from: torch.Tensor, pose_to: torch.Tensor, disparity: torch.Tensor,
                        intrinsics: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Grid disparity ``(h, w)`` of camera ``pose_to`` from camera ``pose_from``'s ``(h, w)`` grid disparity: each
    cell's point moved into the new camera and splatted to its nearest cell (the nearest point wins); cells no
    point lands in get the median of those that did. Poses world_from_cam ``(4, 4)``, grid intrinsics ``(4,)``.
    Returns (disparity, known): ``known`` is 1 where a point landed, 0 where the median filled in."""
    h, w = disparity.shape
    dev = disparity.device
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64, device=dev),
                            torch.arange(w, dtype=torch.float64, device=dev), indexing="ij")
    disp = disparity.to(torch.float64).clamp_min(1e-6)
    points = torch.stack([(xs - cx) / fx / disp, (ys - cy) / fy / disp, 1.0 / disp], dim=-1).reshape(-1, 3)
    to_from = (se3.inverse(pose_to) @ pose_from).to(dev, torch.float64)
    moved = points @ to_from[:3, :3].T + to_from[:3, 3]
    z = moved[:, 2]
    front = z > 1e-6
    u = torch.round(moved[:, 0] / z.clamp_min(1e-6) * fx + cx)
    v = torch.round(moved[:, 1] / z.clamp_min(1e-6) * fy + cy)
    inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    out = torch.zeros(h * w, dtype=torch.float64, device=dev)
    if bool(inside.any()):
        index = (v[inside] * w + u[inside]).long()
        out.scatter_reduce_(0, index, 1.0 / z[inside], reduce="amax", include_self=True)
    filled = out > 0
    fill = out[filled].median() if bool(filled.any()) else disp.median()
    return (torch.where(filled, out, fill).reshape(h, w).to(disparity.dtype),
            filled.reshape(h, w).to(disparity.dtype))


class Tracker:
    """Aligns frames in arrival order; feed references with :meth:`set_reference` as mapping produces them."""

    def __init__(self, params: MotionParams, flow: FlowParams):
        self.params = params
        scale = params.flow_downscale
        # at 1/scale a grid cell is grid/scale pixels and grid coordinates come out the same (frames.py)
        self.flow = replace(flow, grid=flow.grid // scale, fb_sigma=flow.fb_sigma / scale)
        self.reference: Reference | None = None  # what frames are aligned to: mapping's, or a carried-over one
        self._mapped: Reference | None = None  # mapping's newest
        self._head: Reference | None = None  # a keyframe promoted by tracking while mapping is behind
        self._newest_keyframe = self._previous_keyframe = -1  # seqs of the last two keyframes tracking saw
        self._ref_small: np.ndarray | None = None
        self._history: list[Tracked] = []  # the last two tracked frames (constant-velocity prediction)

    def set_reference(self, ref: Reference) -> None:
        """Mapping's newest keyframe. Tracking uses it unless it holds a carried-over reference and ``ref`` is
        older than the keyframe before the newest one tracking has seen (mapping is that far behind)."""
        self._mapped = ref
        behind = self._head is not None and ref.seq < self._previous_keyframe
        if not behind:
            self._head = None
            self._use(ref)

    def promote(self, seq: int, stamp: int, image: np.ndarray, pose: torch.Tensor) -> None:
        """Keyframe ``seq`` was tracked to ``pose`` (``image``: (H, W) grey, working resolution). When mapping
        does not yet hold the keyframe before it, it becomes the reference, with the current reference's depth
        carried over; otherwise mapping's reference stays (it is at most one keyframe back, and refined)."""
        self._previous_keyframe, newest = self._newest_keyframe, seq
        self._newest_keyframe = newest
        if self._mapped is not None and self._mapped.seq >= self._previous_keyframe:
            return
        ref = self.reference
        disparity, known = propagate_disparity(ref.pose, pose, ref.disparity, ref.intrinsics)
        self._head = Reference(seq, stamp, pose, disparity, ref.intrinsics, image, (ref.stamp, ref.pose), known)
        self._use(self._head)

    def _use(self, ref: Reference) -> None:
        scale = self.params.flow_downscale
        h, w = ref.image.shape
        self._ref_small = ref.image if scale == 1 else cv2.resize(ref.image, (w // scale, h // scale),
                                                                  interpolation=cv2.INTER_AREA)
        self.reference = ref

    def reset(self) -> None:
        """A new stream: forget the reference and the motion."""
        self.reference, self._ref_small, self._history = None, None, []
        self._mapped = self._head = None
        self._newest_keyframe = self._previous_keyframe = -1

    def predict(self, stamp: int) -> torch.Tensor:
        """Constant-velocity world_from_cam at time ``stamp``: from the last two tracked frames while tracking
        holds, else from the motion between the reference and the keyframe before it (mapping's estimate)."""
        ref = self.reference
        hist = self._history
        if len(hist) == 2 and hist[0].ok and hist[1].ok and hist[1].stamp >= ref.stamp:
            return _extrapolate(hist[0].stamp, hist[0].pose, hist[1].stamp, hist[1].pose, stamp)
        if ref.previous is not None:
            return _extrapolate(*ref.previous, ref.stamp, ref.pose, stamp)
        return ref.pose

    def track(self, seq: int, stamp: int, image: np.ndarray) -> Tracked | None:
        """Pose of frame ``seq`` (``image``: (h, w) grey or (h, w, 3), any size with the working aspect ratio);
        None before the first reference (the map has not started)."""
        ref = self.reference
        if ref is None:
            return None
        small = self._ref_small
        size = (small.shape[1], small.shape[0])
        grey = core_flow.to_grey(np.asarray(image))
        if grey.shape[:2] != small.shape:
            grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA if grey.shape[1] > size[0] else cv2.INTER_LINEAR)
        guess = self.predict(stamp)
        scale = self.params.flow_downscale
        init = induced_flow_field(ref.pose, guess, ref.disparity, ref.intrinsics, GRID // scale)
        ft = core_flow.flow_targets(small, grey, self.flow, init)
        confidence = ft.confidence * photometric_agreement(small, grey, ft.target, self.flow.grid)
        if ref.known is not None:  # a carried-over depth says nothing where no point landed
            confidence = confidence * ref.known.cpu().numpy()
        target = torch.from_numpy(ft.target)[None].to(ref.pose.device)
        conf = torch.from_numpy(confidence.astype(np.float32))[None].to(ref.pose.device)
        res = motion.align(guess, ref.pose[None], ref.disparity[None], target, conf, ref.intrinsics, self.params)
        cells = ref.disparity.numel()
        ok = (res.ok and res.weight >= TRACK_MIN_SHARE * cells and res.rms <= TRACK_MAX_RMS
              and bool(torch.isfinite(res.pose).all()))
        pose = res.pose if ok else guess
        out = Tracked(seq, stamp, pose, ref.seq, ok)
        self._history = (self._history + [out])[-2:]
        return out
