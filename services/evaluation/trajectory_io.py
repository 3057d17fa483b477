"""Trajectory files: TUM (``t tx ty tz qx qy qz qw``) and KITTI (12 numbers, row-major 3x4) <-> poses.

Poses are ``world_from_cam`` (camera-to-world) ``(N, 4, 4)`` float64 (docs/CONVENTIONS.md). TUM quaternions
are Hamilton ``(x, y, z, w)``. KITTI files carry no time: the frame index is used as the timestamp.
:func:`tum_text` is the one TUM writer (the runner's files, the gateway's ``?format=tum``, the synthetic world's
``groundtruth.txt``).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from services.common.rotations import quaternion_to_rotation, rotation_to_quaternion  # noqa: F401 (re-exported)

FORMATS = ("tum", "kitti")
TUM_DECIMALS = 9
"""Decimals of TUM values: nanometres, and 1e-9 in the quaternions (trailing zeros are left out)."""
TUM_COMMENT = "timestamp tx ty tz qx qy qz qw (world_from_cam)"


class TrajectoryFormatError(ValueError):
    """A trajectory file that cannot be parsed in the requested format."""


@dataclass(frozen=True)
class Trajectory:
    """Timestamped poses."""

    timestamps: np.ndarray  # (N,) float64 seconds (KITTI: frame index)
    world_from_cam: np.ndarray  # (N, 4, 4) float64

    def __post_init__(self) -> None:
        n = len(self.timestamps)
        if self.timestamps.shape != (n,) or self.world_from_cam.shape != (n, 4, 4):
            raise ValueError(f"timestamps (N,) and poses (N,4,4) expected, got "
                             f"{self.timestamps.shape}, {self.world_from_cam.shape}")

    @property
    def positions(self) -> np.ndarray:
        """Camera centres in the world frame, ``(N, 3)``."""
        return self.world_from_cam[:, :3, 3]


def _load_rows(path: Path, width: int, fmt: str) -> np.ndarray:
    rows = []
    for lineno, line in enumerate(Path(path).read_text().splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != width:
            raise TrajectoryFormatError(f"{path}:{lineno}: {fmt} expects {width} numbers, got {len(parts)}")
        try:
            rows.append([float(p) for p in parts])
        except ValueError as exc:
            raise TrajectoryFormatError(f"{path}:{lineno}: not a number: {exc}") from None
    if not rows:
        raise TrajectoryFormatError(f"{path}: no poses")
    return np.asarray(rows, dtype=np.float64)


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM file (``#`` comments, blank lines skipped)."""
    a = _load_rows(Path(path), 8, "TUM")
    poses = np.tile(np.eye(4), (len(a), 1, 1))
    poses[:, :3, :3] = quaternion_to_rotation(a[:, 4:8])
    poses[:, :3, 3] = a[:, 1:4]
    return Trajectory(a[:, 0], poses)


def read_kitti(path: str | Path) -> Trajectory:
    """Read a KITTI pose file (row-major 3x4 per line); timestamps are frame indices."""
    a = _load_rows(Path(path), 12, "KITTI")
    poses = np.tile(np.eye(4), (len(a), 1, 1))
    poses[:, :3, :] = a.reshape(-1, 3, 4)
    return Trajectory(np.arange(len(a), dtype=np.float64), poses)


def read_trajectory(path: str | Path, fmt: str) -> Trajectory:
    """Read ``path`` in format ``fmt`` (one of :data:`FORMATS`)."""
    if fmt not in FORMATS:
        raise ValueError(f"format must be one of {FORMATS}, got {fmt!r}")
    return read_tum(path) if fmt == "tum" else read_kitti(path)


def tum_timestamp(t_ns: int, decimals: int = TUM_DECIMALS) -> str:
    """Seconds with ``decimals`` decimals from integer nanoseconds, exact (truncated, no float rounding):
    ``tum_timestamp(1_500_000_000, 6) == "1.500000"``."""
    ticks = int(t_ns) // 10 ** (9 - decimals)
    return f"{ticks // 10 ** decimals}.{ticks % 10 ** decimals:0{decimals}d}"


def tum_text(stamps: Sequence[str], world_from_cam: np.ndarray, comment: str | None = None) -> str:
    """TUM lines ``stamp tx ty tz qx qy qz qw`` of ``(N, 4, 4)`` poses, one per (already formatted) stamp, after an
    optional ``# comment`` line; values with :data:`TUM_DECIMALS` decimals."""
    poses = np.asarray(world_from_cam, np.float64)
    if poses.shape != (len(stamps), 4, 4):
        raise ValueError(f"need (N, 4, 4) poses for N={len(stamps)} stamps, got {poses.shape}")
    values = np.concatenate([poses[:, :3, 3], rotation_to_quaternion(poses[:, :3, :3])], axis=1)
    values = np.round(values, TUM_DECIMALS) + 0.0  # + 0.0: -0.0 (from rounding a tiny negative) prints as 0
    # fixed point, then trailing zeros cut: "5", "0.1", "-1.25" (the fractional part always has a dot to stop at)
    lines = [f"# {comment}"] if comment else []
    lines += [stamp + " " + " ".join(f"{v:.{TUM_DECIMALS}f}".rstrip("0").rstrip(".") for v in row)
              for stamp, row in zip(stamps, values.tolist())]
    return "\n".join(lines) + "\n" if lines else ""


def write_tum(path: str | Path, traj: Trajectory) -> None:
    """Write ``traj`` as TUM (timestamps and values with 9 decimals)."""
    stamps = [f"{t:.{TUM_DECIMALS}f}" for t in traj.timestamps.tolist()]
    Path(path).write_text(tum_text(stamps, traj.world_from_cam, TUM_COMMENT))


def write_kitti(path: str | Path, traj: Trajectory) -> None:
    """Write ``traj`` as KITTI (3x4 row-major, 12 numbers a line; timestamps are dropped)."""
    rows = traj.world_from_cam[:, :3, :].reshape(-1, 12)
    Path(path).write_text("\n".join(" ".join(f"{v:.9e}" for v in row) for row in rows) + "\n")
