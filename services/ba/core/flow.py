"""Flow targets for BA edges: OpenCV DIS optical flow, sampled to the 1/8 grid, forward-backward confidence."""
from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np

from services.ba.core.params import FlowParams

_PRESETS = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST, "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
            "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}


class FlowTargets(NamedTuple):
    """Where each grid cell of keyframe i lands in keyframe j."""

    target: np.ndarray  # (h, w, 2) float32 grid coordinates (x, y) in keyframe j
    confidence: np.ndarray  # (h, w) float32 in [0, 1]
    flow: np.ndarray  # (H, W, 2) float32 forward flow at working resolution (reusable as an initial flow)


def to_grey(image: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB or ``(H, W)`` uint8 grey -> ``(H, W)`` uint8 grey."""
    if image.dtype != np.uint8 or image.ndim not in (2, 3):
        raise ValueError(f"uint8 (H,W) or (H,W,3) image expected, got {image.dtype} {image.shape}")
    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


def dis_flow(image_a: np.ndarray, image_b: np.ndarray, params: FlowParams,
             init_flow: np.ndarray | None = None) -> np.ndarray:
    """Dense flow ``(H, W, 2)`` float32 (dx, dy in pixels) from ``image_a`` to ``image_b`` (uint8 grey/RGB)."""
    if params.preset not in _PRESETS:
        raise ValueError(f"preset must be one of {sorted(_PRESETS)}, got {params.preset!r}")
    dis = cv2.DISOpticalFlow_create(_PRESETS[params.preset])
    if params.finest_scale is not None:
        dis.setFinestScale(params.finest_scale)
    if params.patch_stride is not None:
        dis.setPatchStride(params.patch_stride)
    a, b = to_grey(image_a), to_grey(image_b)
    if a.shape != b.shape:
        raise ValueError(f"images differ in size: {a.shape} vs {b.shape}")
    if init_flow is None:
        return dis.calc(a, b, None)
    # DIS refines a flow passed to calc() when it has the image's size and is float32 2-channel
    return dis.calc(a, b, np.ascontiguousarray(init_flow, dtype=np.float32))


def _block_mean(x: np.ndarray, grid: int) -> np.ndarray:
    """float32 means of ``grid`` x ``grid`` blocks, summed in float64. OpenCV's area resize at an integer factor is
    exactly that mean, ~15x faster than numpy's over a reshaped view. Their float32 rounding alone moved a two-lap
    orbit's ATE: 0.16 m summed in numpy's order, 0.21 m in OpenCV's, 0.14 m in float64 (tests/test_landmarks.py)."""
    h, w = x.shape[0] // grid, x.shape[1] // grid
    block = np.ascontiguousarray(x[: h * grid, : w * grid], dtype=np.float64)
    return cv2.resize(block, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32)


def flow_targets(image_i: np.ndarray, image_j: np.ndarray, params: FlowParams,
                 init_flow: np.ndarray | None = None, init_backward: np.ndarray | None = None) -> FlowTargets:
    """Grid flow targets of edge ``(i, j)`` from working-resolution images (H, W multiples of ``grid``).

    The target of cell (r, c) is the mean landing point of its 8x8 block, i.e. the flow at the cell centre
    ``(8c + 3.5, 8r + 3.5)`` for locally affine flow, converted to grid coordinates with
    ``x_grid = (x + 0.5)/8 - 0.5`` (docs/CONVENTIONS.md). Confidence is the block mean of
    ``exp(-|F(p) + B(p + F(p))|^2 / (2 sigma^2))`` (0 where ``p + F(p)`` leaves the image). ``init_flow`` and
    ``init_backward`` (``(H, W, 2)`` float32) start DIS from a predicted forward / backward flow.
    """
    return _targets(*_flows(image_i, image_j, params, init_flow, init_backward), params)


def pair_targets(image_i: np.ndarray, image_j: np.ndarray, params: FlowParams, init_flow: np.ndarray | None = None,
                 init_backward: np.ndarray | None = None) -> tuple[FlowTargets, FlowTargets]:
    """Targets of both edges ``(i, j)`` and ``(j, i)`` from the same two DIS flows: each direction's flow is the
    other's forward-backward check, so a pair costs two flows instead of four (same results as two
    :func:`flow_targets` calls)."""
    fwd, bwd = _flows(image_i, image_j, params, init_flow, init_backward)
    return _targets(fwd, bwd, params), _targets(bwd, fwd, params)


def _flows(image_i, image_j, params: FlowParams, init_flow, init_backward) -> tuple[np.ndarray, np.ndarray]:
    height, width = to_grey(image_i).shape
    if height % params.grid or width % params.grid:
        raise ValueError(f"image size {height}x{width} is not a multiple of {params.grid}")
    return dis_flow(image_i, image_j, params, init_flow), dis_flow(image_j, image_i, params, init_backward)


def _targets(fwd: np.ndarray, bwd: np.ndarray, params: FlowParams) -> FlowTargets:
    height, width = fwd.shape[:2]
    xs, ys = np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32))
    land = fwd + np.stack([xs, ys], -1)
    bwd_at = cv2.remap(bwd, land, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    fb = fwd + bwd_at
    fb_err2 = np.einsum("ijk,ijk->ij", fb, fb)
    land_x, land_y = land[..., 0], land[..., 1]
    inside = (land_x >= -0.5) & (land_x <= width - 0.5) & (land_y >= -0.5) & (land_y <= height - 0.5)
    conf = np.exp(-0.5 * fb_err2 / params.fb_sigma**2) * inside  # float32; its means summed in float64
    target = (_block_mean(land, params.grid) + 0.5) / params.grid - 0.5
    return FlowTargets(target.astype(np.float32), _block_mean(conf, params.grid), fwd)


def edge_targets(images: list[np.ndarray], edges: list[tuple[int, int]],
                 params: FlowParams) -> tuple[np.ndarray, np.ndarray]:
    """Grid targets ``(E, h, w, 2)`` and confidences ``(E, h, w)`` (float32) of the directed ``edges`` (i, j)
    between working-resolution ``images``; an edge and its reverse share one pair of DIS flows."""
    done: dict[tuple[int, int], FlowTargets] = {}
    for i, j in edges:
        if (i, j) not in done:
            done[(i, j)], done[(j, i)] = pair_targets(images[i], images[j], params)
    return (np.stack([done[e].target for e in edges]), np.stack([done[e].confidence for e in edges]))


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
