"""Exports the tools people already use can open: PLY point cloud, depth maps, keyframe images and a COLMAP model
(:mod:`services.mapstore.colmap`), one keyframe at a time (:class:`ExportWriter`).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
from services.common import ply
from services.mapstore.colmap import ColmapImage, ColmapParams, ColmapWriter
from services.mapstore.core.keyframe import KeyframeDepth

log = logging.getLogger(__name__)

DEPTH_PNG_SCALE = 1000.0
"""16-bit depth PNGs store millimetres (depth · 1000), 0 = unknown."""


# ----- PLY ------------------------------------------------------------------------------------
def write_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray, label_rgb: np.ndarray | None = None,
              binary: bool = True) -> Path:
    """Write the map: xyz (N, 3) float, rgb (N, 3) uint8[, label_rgb (N, 3) uint8 colour of each point's label];
    binary_little_endian (True) or ascii. Layouts: :mod:`services.common.ply`."""
    if label_rgb is None:
        rec = ply.records(ply.VERTEX, xyz, rgb)
    else:
        label_rgb = np.asarray(label_rgb)
        if label_rgb.shape != (len(xyz), 3):
            raise ValueError(f"label_rgb must be ({len(xyz)}, 3), got {label_rgb.shape}")
        rec = ply.records(ply.LABEL_COLOURED, xyz, rgb, **{f"label_{c}": label_rgb[:, i]
                                                           for i, c in enumerate(("red", "green", "blue"))})
    return ply.write(path, rec, text=not binary, comments=["KM-ViPE map"])


read_ply = ply.read


def label_palette(n_labels: int) -> np.ndarray:
    """(n_labels, 3) uint8 distinct colours (golden-ratio hues)."""
    hues = (np.arange(n_labels) * 0.61803398875 % 1.0 * 180).astype(np.uint8)
    hsv = np.stack([hues, np.full(n_labels, 200, np.uint8), np.full(n_labels, 255, np.uint8)], 1)
    return cv2.cvtColor(hsv[None], cv2.COLOR_HSV2RGB)[0]


# ----- depth maps -------------------------------------------------------------------------------
def depth_image(depth: KeyframeDepth, upsample: int = 8) -> np.ndarray:
    """(h·s, w·s) float32 depth (1/disparity, 0 = unknown), nearest-upsampled from the grid by s."""
    disp = depth.disparity.astype(np.float64)
    z = np.where(disp > 0, 1.0 / np.where(disp > 0, disp, 1.0), 0.0).astype(np.float32)
    return np.repeat(np.repeat(z, upsample, axis=0), upsample, axis=1)


def depth_map_path(folder: Path, kf_id: int, metric: bool) -> Path:
    """Where keyframe ``kf_id``'s depth map goes: `<kf>.png` when metric, else `<kf>.npz`."""
    return Path(folder) / f"{kf_id:06d}.{'png' if metric else 'npz'}"


def read_depth_map(path: Path) -> np.ndarray:
    """A depth map `write_depth_maps` wrote, back as float64 depth (metres from a PNG, the map's scale from an npz;
    0 = unknown)."""
    path = Path(path)
    if path.suffix == ".npz":
        with np.load(path) as data:
            return data["depth"].astype(np.float64)
    mm = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if mm is None:
        raise ValueError(f"cannot read the depth map {path}")
    return mm.astype(np.float64) / DEPTH_PNG_SCALE


def write_depth_maps(folder: Path, depths: dict[int, KeyframeDepth], metric: bool, upsample: int = 8) -> list[Path]:
    """One depth map per keyframe: `<kf>.png` (uint16 mm) when metric, else `<kf>.npz` (float32, arbitrary scale);
    one of the other kind left by an earlier export (the map became metric since) is removed.

    Depths are nearest-upsampled from the 1/8 grid by `upsample` (8 → working resolution).
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for kf_id in sorted(depths):
        z = depth_image(depths[kf_id], upsample)
        path = depth_map_path(folder, kf_id, metric)
        if metric:
            mm = np.clip(np.rint(z * DEPTH_PNG_SCALE), 0, 65535).astype(np.uint16)
            if not cv2.imwrite(str(path), mm):
                raise OSError(f"could not write {path}")
        else:
            np.savez_compressed(path, depth=z, metric=False)
        depth_map_path(folder, kf_id, not metric).unlink(missing_ok=True)
        out.append(path)
    return out


def image_name(kf_id: int) -> str:
    """A keyframe's image file name (under `images/`) and COLMAP image name."""
    return f"{kf_id:06d}.jpg"


def is_rigid(pose: np.ndarray, tol: float = 1e-3) -> bool:
    """A finite world_from_cam whose rotation is orthonormal (a diverged BA can publish one that is not)."""
    rot = pose[:3, :3]
    return bool(np.all(np.isfinite(pose)) and np.allclose(rot.T @ rot, np.eye(3), atol=tol))


def write_keyframe_files(out: Path, kf_id: int, depth: KeyframeDepth, jpeg: bytes | None, metric: bool) -> list[Path]:
    """A keyframe's depth map (`depth/`) and, when given, its image (`images/`): what the export writes of a
    keyframe apart from the COLMAP model; the paths written."""
    paths = write_depth_maps(Path(out) / "depth", {kf_id: depth}, metric)
    if jpeg is not None:
        paths.append(write_image(out, image_name(kf_id), jpeg))
    return paths


def write_image(out: Path, name: str, jpeg: bytes) -> Path:
    """A keyframe's JPEG as `images/<name>`."""
    path = Path(out) / "images" / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(jpeg)
    return path


class Exported(NamedTuple):
    """A folded keyframe's files written to the export folder when it folded."""

    metric: bool  # the kind of depth map written (png mm, or npz)
    image: bool  # its image too (not for a pose no camera can have)


class FoldedExports:
    """The depth maps and images of keyframes as they fold (their depth and pose are final then) into ``out``, so
    the end of stream writes only the live keyframes' files, the point cloud and the COLMAP model; ``written``
    says what is there."""

    def __init__(self, out: Path | None) -> None:
        self.out = out
        self.written: dict[int, Exported] = {}

    def write(self, kf_id: int, depth: KeyframeDepth, pose: np.ndarray, jpeg_of, metric: bool) -> None:
        """One keyframe; ``jpeg_of()`` reads its image (only for a pose a camera can have, as the export). One
        that cannot be written is left to the end of stream's export (logged)."""
        jpeg = jpeg_of() if is_rigid(pose) else None
        try:
            write_keyframe_files(self.out, kf_id, depth, jpeg, metric)
        except OSError as exc:
            log.warning("folded keyframe not exported yet", extra={"seq": kf_id, "error": str(exc)})
            return
        self.written[kf_id] = Exported(metric, jpeg is not None)


# ----- everything at once --------------------------------------------------------------------------
class ExportResult(NamedTuple):
    """Paths written by `export_all`."""

    ply: Path
    depth_maps: list[Path]
    colmap: Path
    images: list[Path]


def export_all(out: Path, xyz: np.ndarray, rgb: np.ndarray, depths: dict[int, KeyframeDepth],
               cameras: dict[int, ColmapImage], metric: bool, jpegs: dict[int, bytes] | None = None,
               label_rgb: np.ndarray | None = None, colmap: ColmapParams | None = None) -> ExportResult:
    """Write `map.ply`, `depth/`, `colmap/` (cameras, images, points3D; .txt and .bin) and `images/`.

    Args:
        out: output folder.
        xyz, rgb, label_rgb: the fused map points, (N, 3) float / uint8 / uint8.
        depths: latest geometry per keyframe; cameras: pose, intrinsics and image name per keyframe.
        metric: depth maps as 16-bit PNG mm (True) or npz (scale-free map).
        jpegs: keyframe images (written to images/ under their camera name).
        colmap: which points the COLMAP model carries (defaults: ColmapParams()).
    """
    writer = ExportWriter(out, xyz, rgb, metric, label_rgb, colmap)
    for kf_id in sorted(set(depths) | set(cameras)):
        depth, camera = depths.get(kf_id), cameras.get(kf_id)
        if depth is not None:
            writer.add_depth(kf_id, depth)
        if camera is not None:
            writer.add_camera(camera, (jpegs or {}).get(kf_id), depth)
    return writer.close()


class ExportWriter:
    """`export_all` one keyframe at a time (ascending ids): the point cloud at once, then each keyframe's depth
    map, image and the map points its camera sees as it is added (the COLMAP model is written on close), so an
    export holds one keyframe's depth and image at a time."""

    def __init__(self, out: Path, xyz: np.ndarray, rgb: np.ndarray, metric: bool,
                 label_rgb: np.ndarray | None = None, colmap: ColmapParams | None = None) -> None:
        self.out = Path(out)
        self.metric = metric
        self.n_points = len(xyz)
        self.ply = write_ply(self.out / "map.ply", xyz, rgb, label_rgb)
        (self.out / "depth").mkdir(parents=True, exist_ok=True)
        self.colmap = ColmapWriter(self.out / "colmap", xyz, rgb, colmap)
        self.depth_paths: list[Path] = []
        self.image_paths: list[Path] = []

    def add_depth(self, kf_id: int, depth: KeyframeDepth) -> None:
        self.depth_paths += write_depth_maps(self.out / "depth", {kf_id: depth}, self.metric)

    def add_camera(self, camera: ColmapImage, jpeg: bytes | None = None, depth: KeyframeDepth | None = None) -> None:
        """A keyframe's camera and image; with its ``depth``, the map points it sees join the COLMAP model."""
        self.colmap.add(camera, depth)
        if jpeg is not None:
            self.image_paths.append(write_image(self.out, camera.name, jpeg))

    def add(self, kf_id: int, depth: KeyframeDepth, camera: ColmapImage | None, jpeg: bytes | None = None) -> None:
        """A keyframe's depth map and, unless None (an invalid pose), its camera, image and observations."""
        self.add_depth(kf_id, depth)
        if camera is not None:
            self.add_camera(camera, jpeg, depth)

    def add_written(self, kf_id: int, depth: KeyframeDepth, camera: ColmapImage | None, image: bool) -> None:
        """A keyframe whose depth map (and ``image``, if it has one) :func:`write_keyframe_files` wrote earlier:
        its camera and observations join the COLMAP model and its files are listed, none written again."""
        self.depth_paths.append(depth_map_path(self.out / "depth", kf_id, self.metric))
        if camera is not None:
            self.colmap.add(camera, depth)
            if image:
                self.image_paths.append(self.out / "images" / camera.name)

    def close(self) -> ExportResult:
        colmap = self.colmap.close()
        log.info("exported %d points, %d depth maps, %d cameras to %s", self.n_points, len(self.depth_paths),
                 self.colmap.count, self.out)
        return ExportResult(self.ply, self.depth_paths, colmap, self.image_paths)
