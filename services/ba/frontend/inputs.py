"""What the frontend takes in: a keyframe (working-resolution image, intrinsics, optional codes and disparity
prior, tracking's pose guess) and a frame (its image, or where tracking already put it), and the checks a keyframe
must pass before it joins the graph."""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from services.ba.core import flow as core_flow
from services.ba.frontend.graph import GRID, NativeCodes


class KeyframeInput(NamedTuple):
    seq: int
    t_ns: int
    image: np.ndarray  # (H, W, 3) uint8 RGB or (H, W) grey, working resolution (multiples of 8)
    intrinsics: np.ndarray  # (4,) float64 working-resolution (fx, fy, cx, cy)
    codes: np.ndarray | None = None  # (H/8, W/8, K) feature codes in the version all graph codes share
    disparity_prior: np.ndarray | None = None  # (H/8, W/8) 1/m, 0 = none
    native_codes: NativeCodes | None = None  # the codes as received, for KeyframeGraph.recode on a new basis
    pose_guess: torch.Tensor | None = None  # (4, 4) world_from_cam from tracking: a better start than constant velocity
    realtime: bool = False  # from a live stream: mapping must keep up (cheaper edge flows, FrontendParams.live_*)
    defer_ba: bool = False  # mapping is behind a live camera: align this keyframe and leave the window BA to a
    # later one (at most FrontendParams.live_max_deferred in a row), so the graph keeps every keyframe


class FrameInput(NamedTuple):
    seq: int
    t_ns: int
    image: np.ndarray  # (h', w') uint8 grey (or RGB), same aspect ratio as the working image
    tracked: tuple[int, torch.Tensor] | None = None  # (keyframe seq, (4, 4) keyframe_from_cam) from tracking
    interpolate_only: bool = False  # pose it between its keyframes by time, spend no flow on it
    tracked_world: torch.Tensor | None = None  # (4, 4) world_from_cam from tracking, when its keyframe is not mapped
    tracked_flow: tuple[int, torch.Tensor, torch.Tensor] | None = None  # tracking's flow: its reference keyframe's
    # seq, (h, w, 2) float32 grid targets and (h, w) float32 confidence (frames.FramePoses.resolve)


def check_keyframe(kf: KeyframeInput) -> tuple[np.ndarray, tuple[int, int]]:
    """The keyframe's grey image and its flow grid (h/8, w/8); ValueError naming what is wrong otherwise."""
    grey = core_flow.to_grey(np.asarray(kf.image))
    height, width = grey.shape
    if height % GRID or width % GRID:
        raise ValueError(f"keyframe {kf.seq}: working size {width}x{height} is not a multiple of {GRID}")
    hw = (height // GRID, width // GRID)
    for name in ("codes", "disparity_prior"):
        grid = getattr(kf, name)
        if grid is not None and np.asarray(grid).shape[:2] != hw:
            raise ValueError(f"keyframe {kf.seq}: {name} grid {np.asarray(grid).shape[:2]} must be {hw}")
    if np.asarray(kf.intrinsics).shape != (4,):
        raise ValueError(f"keyframe {kf.seq}: intrinsics (4,) expected")
    return grey, hw
