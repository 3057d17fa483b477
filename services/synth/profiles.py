"""Named hand-held motion profiles for the motion robustness suite (issue 13): exact world_from_cam trajectories in
the synthetic room, and the world that renders them. Pure: arrays in, arrays out, no I/O.

Every profile starts in the free floor space of the room and keeps a slow pitch (±2°) and roll (±1.5°) wobble, as a
hand does. Rates are per frame; ``n`` frames (default 120, i.e. 4 s at 30 Hz).

  rot0                       walking sideways 1 cm/frame, no yaw (the easy baseline)
  rot0.5, rot1, rot2, rot3   the same walk while yawing back and forth, peak rate 0.5 / 1 / 2 / 3 °/frame
  pure_rotation              walking, then n/3 frames of pure yaw at 1 °/frame (no parallax), then walking again
  spin                       yaw at 1 °/frame from one spot for the whole sequence (rotation only: no path)
  turn180                    a 180° turn (1.5 °/frame at n = 120) while walking 1 cm/frame
  fast_pan                   yaw back and forth at up to 4 °/frame, 0.5 cm/frame of translation
  backwards                  walking backwards (along the camera's -z) 1.5 cm/frame with a little yaw
  low_texture                walking along a bare wall 1.4 m away, yaw ±0.5 °/frame, wall texture at 20 % contrast
  fovN (N in 40..110)        rot1 through an N° (horizontal) lens, e.g. fov40, fov80, fov110

The motions of the first ten are exactly those bench/robustness.py had inline before this module (the numbers in
docs/BENCHMARKS.md stay comparable).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from services.synth.camera import look_at
from services.synth.config import SynthConfig
from services.synth.layout import ROOM_FACE_LABELS
from services.synth.render import SynthWorld

SYNTHETIC = ("rot0.5", "rot1", "rot2", "rot3", "pure_rotation", "spin", "turn180", "fast_pan", "backwards",
             "low_texture", "fov40", "fov80", "fov110")
FOV_RANGE_DEG = (40.0, 110.0)  # the lenses the issue asks about
DEFAULT_FOV_DEG = 60.0
LOW_WALL_CONTRAST = 0.2  # a painted wall keeps faint marks; 0 would be a blank no real room has
WALK_STEP_M = 0.01  # per frame: 30 cm/s, a slow hand-held walk
SWING_PERIOD = 120  # frames of one back-and-forth yaw swing


@dataclass(frozen=True)
class Profile:
    """One named motion: what the camera does and what it looks through."""

    name: str
    poses: np.ndarray  # (n, 4, 4) float64 world_from_cam, OpenCV camera axes, metres
    hfov_deg: float  # horizontal field of view, degrees
    wall_contrast: float = 1.0  # texture contrast on the room's walls (1: the room as built)
    rotation_only: tuple[int, int] | None = None  # frames [a, b) with no translation (no parallax), if any


def _poses(position: np.ndarray, yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray,
           forward=(0.0, 1.0, 0.0)) -> np.ndarray:
    """world_from_cam (n, 4, 4) from positions (n, 3) m and yaw / pitch / roll (n,) degrees: looking along
    ``forward`` at zero yaw, yaw about world up, pitch and roll about the camera's own x and z axes."""
    out = np.zeros((len(yaw), 4, 4))
    for i, p in enumerate(position):
        base = look_at(p, p + np.asarray(forward))
        out[i] = base
        turn = Rotation.from_euler("z", yaw[i], degrees=True).as_matrix()
        tilt = Rotation.from_euler("XZ", [pitch[i], roll[i]], degrees=True).as_matrix()  # intrinsic: x, then z
        out[i, :3, :3] = turn @ base[:3, :3] @ tilt
    return out


def _swing(n: int, peak_rate: float, period: int = SWING_PERIOD) -> np.ndarray:
    """Back-and-forth angle (n,) degrees whose rate peaks at ``peak_rate`` °/frame."""
    return peak_rate * period / (2 * math.pi) * np.sin(2 * math.pi * np.arange(n) / period)


def _walk(n: int, step: float, direction=(1.0, 0.0, 0.0), start=(2.9, 1.4, 1.4)) -> np.ndarray:
    """Positions (n, 3) m: ``step`` m/frame along ``direction`` from ``start``."""
    return np.asarray(start) + step * np.arange(n)[:, None] * np.asarray(direction)


def _wobble(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Pitch and roll (n,) degrees: slow, incommensurate, as a hand holds a camera."""
    i = np.arange(n)
    return 2.0 * np.sin(2 * math.pi * i / 97), 1.5 * np.sin(2 * math.pi * i / 71 + 1.0)


def _rate_of(name: str, prefix: str) -> float | None:
    """The number after ``prefix`` in a profile name (``rot1.5`` → 1.5), None if it is not one."""
    if not name.startswith(prefix):
        return None
    try:
        return float(name[len(prefix):])
    except ValueError:
        return None


def profile(name: str, n: int = 120) -> Profile:
    """The named profile over ``n`` frames; ValueError naming the known profiles otherwise."""
    if n < 3:
        raise ValueError(f"a profile needs at least 3 frames, got {n}")
    pitch, roll = _wobble(n)
    rate, fov = _rate_of(name, "rot"), _rate_of(name, "fov")
    if fov is not None and not FOV_RANGE_DEG[0] <= fov <= FOV_RANGE_DEG[1]:
        raise ValueError(f"field of view {fov:g}° outside {FOV_RANGE_DEG[0]:g}..{FOV_RANGE_DEG[1]:g}")
    if rate is not None or fov is not None:
        rate = 1.0 if rate is None else rate
        poses = _poses(_walk(n, WALK_STEP_M), _swing(n, rate), pitch, roll)
        return Profile(name, poses, DEFAULT_FOV_DEG if fov is None else fov)
    if name == "pure_rotation":
        third = n // 3
        moved = np.r_[np.arange(third), np.full(third, third), third + np.arange(n - 2 * third)]
        yaw = np.r_[np.zeros(third), np.arange(third) * 1.0, np.full(n - 2 * third, third - 1.0)]
        position = _walk(1, 0)[0] + WALK_STEP_M * moved[:, None] * np.array([1.0, 0, 0])
        return Profile(name, _poses(position, yaw, pitch, roll), DEFAULT_FOV_DEG, rotation_only=(third, 2 * third))
    if name == "spin":
        position = _walk(n, 0.0, start=(3.5, 2.2, 1.4))
        return Profile(name, _poses(position, np.arange(n) * 1.0, pitch, roll), DEFAULT_FOV_DEG, rotation_only=(0, n))
    if name == "turn180":
        poses = _poses(_walk(n, WALK_STEP_M, start=(3.0, 1.6, 1.4)), np.linspace(0, 180, n), pitch, roll)
        return Profile(name, poses, DEFAULT_FOV_DEG)
    if name == "fast_pan":
        return Profile(name, _poses(_walk(n, 0.005), _swing(n, 4.0, 47), pitch, roll), DEFAULT_FOV_DEG)
    if name == "backwards":
        position = _walk(n, 0.015, (0.0, -1.0, 0.0), start=(3.5, 2.5, 1.4))
        return Profile(name, _poses(position, _swing(n, 0.3), pitch, roll), DEFAULT_FOV_DEG)
    if name == "low_texture":
        # the +y wall between the shelf (x < 2.2) and the cabinet (x > 4.6), 1.4 m ahead: mostly bare wall
        step = min(WALK_STEP_M, 1.2 / n)
        position = _walk(n, step, start=(2.9, 4.6, 1.5))
        return Profile(name, _poses(position, _swing(n, 0.5), pitch, roll), DEFAULT_FOV_DEG,
                       wall_contrast=LOW_WALL_CONTRAST)
    raise ValueError(f"unknown profile {name!r}; known: {', '.join(SYNTHETIC)} (rotN: any yaw rate, fovN: any "
                     f"lens in {FOV_RANGE_DEG[0]:g}..{FOV_RANGE_DEG[1]:g}°)")


class _PlainWallWorld(SynthWorld):
    """The synthetic room with its walls' texture contrast scaled about each wall's mean colour."""

    def __init__(self, config: SynthConfig, poses: np.ndarray, wall_contrast: float) -> None:
        self._wall_contrast = wall_contrast  # read by _build_atlas, which SynthWorld.__init__ calls
        super().__init__(config, poses=poses)

    def _build_atlas(self):
        atlas = super()._build_atlas()
        for face, label in enumerate(ROOM_FACE_LABELS):  # textures 0..5 are the room's faces (render.py)
            if label != "wall":
                continue
            r, c = int(atlas.row0[face]), int(atlas.col0[face])
            region = atlas.image[r:r + int(atlas.height[face]), c:c + int(atlas.width[face])]
            texels = region.astype(np.float32)
            mean = texels.reshape(-1, 3).mean(axis=0)
            region[:] = np.clip(mean + self._wall_contrast * (texels - mean) + 0.5, 0, 255).astype(np.uint8)
        return atlas


def profile_world(p: Profile, width: int, height: int, fps: float = 30.0, seed: int = 0) -> SynthWorld:
    """The world that renders profile ``p`` at ``width`` × ``height``: no person, no moved chair (the motion is the
    test, not dynamic objects)."""
    cfg = SynthConfig(n_frames=len(p.poses), width=width, height=height, hfov_deg=p.hfov_deg, fps=fps, seed=seed,
                      person=False, moved_chair=False)
    if p.wall_contrast == 1.0:
        return SynthWorld(cfg, poses=p.poses)
    return _PlainWallWorld(cfg, p.poses, p.wall_contrast)
