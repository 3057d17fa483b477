"""Camera intrinsics and the hand-held trajectory (world_from_cam, OpenCV camera axes)."""

from __future__ import annotations

import numpy as np

from services.synth.config import SynthConfig
from services.synth.layout import table_centre

WORLD_UP = np.array([0.0, 0.0, 1.0])
ORBIT_MID_DEG = -90.0  # the arc is centred on the room's -y side, looking toward +y
SHAKE_FREQS_HZ = (0.23, 0.61, 1.37)  # three incommensurate sinusoids per axis: smooth, non-periodic-looking


def intrinsics(cfg: SynthConfig) -> np.ndarray:
    """Pinhole intrinsics (fx, fy, cx, cy) float64, pixel centres at integer coordinates.

    The image spans [-0.5, W - 0.5], so ``fx = (W / 2) / tan(hfov / 2)`` and ``cx = (W - 1) / 2``.
    """
    fx = (cfg.width / 2.0) / np.tan(np.deg2rad(cfg.hfov_deg) / 2.0)
    return np.array([fx, fx, (cfg.width - 1) / 2.0, (cfg.height - 1) / 2.0])


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """world_from_cam (4, 4) float64 of a camera at ``eye`` (3,) looking at ``target`` (3,), no roll.

    Camera axes: x right, y down, z forward; the world is z up.
    """
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, WORLD_UP)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, y, z], axis=1)
    pose[:3, 3] = eye
    return pose


def _rotvec_to_matrix(w: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vector (3,) radians -> rotation (3, 3)."""
    angle = np.linalg.norm(w)
    if angle < 1e-12:
        return np.eye(3)
    k = w / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


def _orbit_eye(cfg: SynthConfig, s: float) -> np.ndarray:
    theta = np.deg2rad(ORBIT_MID_DEG + cfg.orbit_span_deg * (s - 0.5))
    centre = np.array([cfg.room_size[0] / 2, cfg.room_size[1] / 2])
    xy = centre + cfg.orbit_radius * np.array([np.cos(theta), np.sin(theta)])
    return np.array([xy[0], xy[1], cfg.camera_height])


def _smooth_pose(cfg: SynthConfig, s: float) -> np.ndarray:
    """The trajectory before hand-held shake, at sequence time s."""
    target = table_centre(cfg)
    if cfg.camera == "orbit":
        return look_at(_orbit_eye(cfg, s), target)
    if cfg.camera == "static":
        return look_at(_orbit_eye(cfg, cfg.static_at), target)
    pose = look_at(_orbit_eye(cfg, 0.5), target)  # "pan": yaw about world up, centred on the table
    yaw = np.deg2rad(cfg.pan_span_deg / 2.0) * np.sin(2.0 * np.pi * s)
    pose[:3, :3] = _rotvec_to_matrix(WORLD_UP * yaw) @ pose[:3, :3]
    return pose


def _shake(cfg: SynthConfig, t_s: float, phases: np.ndarray) -> np.ndarray:
    """Small rigid perturbation (4, 4) at time t_s seconds: (tx, ty, tz, rx, ry, rz) sums of sinusoids."""
    freqs = np.asarray(SHAKE_FREQS_HZ)
    waves = np.sin(2.0 * np.pi * freqs[None, :] * t_s + phases).mean(axis=1)  # (6,) in [-1, 1]
    delta = np.eye(4)
    delta[:3, :3] = _rotvec_to_matrix(np.deg2rad(cfg.shake_rotation_deg) * waves[3:])
    delta[:3, 3] = cfg.shake_translation * waves[:3]
    return delta


def trajectory(cfg: SynthConfig) -> np.ndarray:
    """world_from_cam poses (N, 4, 4) float64 for all frames; exactly equal poses in "static" mode."""
    phases = np.random.default_rng([cfg.seed, 1]).uniform(0, 2 * np.pi, (6, len(SHAKE_FREQS_HZ)))
    denom = max(cfg.n_frames - 1, 1)
    poses = np.empty((cfg.n_frames, 4, 4))
    for i in range(cfg.n_frames):
        pose = _smooth_pose(cfg, i / denom)
        if cfg.camera != "static":
            pose = pose @ _shake(cfg, i / cfg.fps, phases)  # shake in the camera frame (hand jitter)
        poses[i] = pose
    return poses
