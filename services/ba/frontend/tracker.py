"""Frame-rate tracking: every frame's pose at once, motion-only against the newest mapped keyframe.

Mapping (window BA) runs per keyframe and takes hundreds of milliseconds; a frame cannot wait for it. The
tracker holds a snapshot of one reference keyframe — its pose, grid disparity and image, as the last BA left
them — and aligns each frame to it: DIS flow from the reference into the frame (at the size frames arrive in),
started from the flow a constant-velocity prediction induces, then the 6-dof Gauss-Newton of
:mod:`services.ba.frontend.motion`. Mapping later revises the pose against the keyframes that bracket the
frame (:mod:`services.ba.frontend.frames`). As in DSO's coarse tracker, the reference only changes when the
mapper hands over a newer keyframe, so tracking never reads state that mapping is changing.
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


class Tracker:
    """Aligns frames in arrival order; feed references with :meth:`set_reference` as mapping produces them."""

    def __init__(self, params: MotionParams, flow: FlowParams):
        self.params = params
        scale = params.flow_downscale
        # at 1/scale a grid cell is grid/scale pixels and grid coordinates come out the same (frames.py)
        self.flow = replace(flow, grid=flow.grid // scale, fb_sigma=flow.fb_sigma / scale)
        self.reference: Reference | None = None
        self._ref_small: np.ndarray | None = None
        self._history: list[Tracked] = []  # the last two tracked frames (constant-velocity prediction)

    def set_reference(self, ref: Reference) -> None:
        scale = self.params.flow_downscale
        h, w = ref.image.shape
        self._ref_small = ref.image if scale == 1 else cv2.resize(ref.image, (w // scale, h // scale),
                                                                  interpolation=cv2.INTER_AREA)
        self.reference = ref

    def reset(self) -> None:
        """A new stream: forget the reference and the motion."""
        self.reference, self._ref_small, self._history = None, None, []

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
        target = torch.from_numpy(ft.target)[None].to(ref.pose.device)
        conf = torch.from_numpy(confidence.astype(np.float32))[None].to(ref.pose.device)
        res = motion.align(guess, ref.pose[None], ref.disparity[None], target, conf, ref.intrinsics, self.params)
        pose = res.pose if res.ok and bool(torch.isfinite(res.pose).all()) else guess
        out = Tracked(seq, stamp, pose, ref.seq, res.ok)
        self._history = (self._history + [out])[-2:]
        return out
