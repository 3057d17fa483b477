"""Exports the tools people already use can open: PLY point cloud, depth maps, COLMAP text cameras.

COLMAP puts pixel centres at +0.5 (the image spans [0, W]); ours are at integers (docs/CONVENTIONS.md),
so principal points gain 0.5 on the way out. COLMAP images store cam_from_world as (qw qx qy qz, t).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from services.common.rotations import rotation_to_quaternion

from services.mapstore.core.keyframe import KeyframeDepth

log = logging.getLogger(__name__)

DEPTH_PNG_SCALE = 1000.0
"""16-bit depth PNGs store millimetres (depth · 1000), 0 = unknown."""


# ----- PLY ------------------------------------------------------------------------------------
def ply_vertex_dtype(with_labels: bool) -> np.dtype:
    """Little-endian vertex record: float x y z, uchar red green blue (+ label_red/green/blue)."""
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
    if with_labels:
        fields += [("label_red", "u1"), ("label_green", "u1"), ("label_blue", "u1")]
    return np.dtype(fields)


_PLY_TYPES = {"f4": "float", "u1": "uchar"}


def write_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray, label_rgb: np.ndarray | None = None,
              binary: bool = True) -> Path:
    """Write a point cloud.

    Args:
        path: output file.
        xyz: (N, 3) float world coordinates; rgb: (N, 3) uint8 colours.
        label_rgb: optional (N, 3) uint8 colour of each point's label.
        binary: binary_little_endian (True) or ascii.
    """
    n = xyz.shape[0]
    if xyz.shape != (n, 3) or rgb.shape != (n, 3) or (label_rgb is not None and label_rgb.shape != (n, 3)):
        raise ValueError("xyz, rgb (and label_rgb) must all be (N, 3)")
    dtype = ply_vertex_dtype(label_rgb is not None)
    rec = np.empty(n, dtype)
    for i, axis in enumerate("xyz"):
        rec[axis] = xyz[:, i]
    for i, ch in enumerate(("red", "green", "blue")):
        rec[ch] = rgb[:, i]
        if label_rgb is not None:
            rec[f"label_{ch}"] = label_rgb[:, i]
    props = "".join(f"property {_PLY_TYPES[dtype[name].str.lstrip('<|')]} {name}\n" for name in dtype.names)
    fmt = "binary_little_endian" if binary else "ascii"
    header = f"ply\nformat {fmt} 1.0\ncomment KM-ViPE map\nelement vertex {n}\n{props}end_header\n"
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        if binary:
            f.write(rec.tobytes())
        else:
            for row in rec.tolist():
                f.write((" ".join(f"{v:.7g}" if isinstance(v, float) else str(v) for v in row) + "\n").encode())
    return path


def read_ply(path: Path) -> np.ndarray:
    """Read a vertex-only PLY (binary_little_endian or ascii, float/uchar properties) as a record array."""
    raw = Path(path).read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    lines = raw[:end].decode("ascii").splitlines()
    if lines[0] != "ply":
        raise ValueError(f"{path} is not a PLY file")
    fmt = next(line.split()[1] for line in lines if line.startswith("format"))
    n = next(int(line.split()[2]) for line in lines if line.startswith("element vertex"))
    types = {"float": "<f4", "uchar": "u1", "double": "<f8", "int": "<i4"}
    dtype = np.dtype([(line.split()[2], types[line.split()[1]]) for line in lines if line.startswith("property")])
    if fmt == "binary_little_endian":
        return np.frombuffer(raw[end:], dtype=dtype, count=n)
    rows = [tuple(r.split()) for r in raw[end:].decode("ascii").splitlines()[:n]]
    return np.array(rows, dtype=[(name, "U32") for name in dtype.names]).astype(dtype)


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


def write_depth_maps(folder: Path, depths: dict[int, KeyframeDepth], metric: bool, upsample: int = 8) -> list[Path]:
    """One depth map per keyframe: `<kf>.png` (uint16 mm) when metric, else `<kf>.npz` (float32, arbitrary scale).

    Depths are nearest-upsampled from the 1/8 grid by `upsample` (8 → working resolution).
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for kf_id in sorted(depths):
        z = depth_image(depths[kf_id], upsample)
        if metric:
            mm = np.clip(np.rint(z * DEPTH_PNG_SCALE), 0, 65535).astype(np.uint16)
            path = folder / f"{kf_id:06d}.png"
            if not cv2.imwrite(str(path), mm):
                raise OSError(f"could not write {path}")
        else:
            path = folder / f"{kf_id:06d}.npz"
            np.savez_compressed(path, depth=z, metric=False)
        out.append(path)
    return out


# ----- COLMAP -----------------------------------------------------------------------------------
def quaternion_wxyz(rotation: np.ndarray) -> np.ndarray:
    """(3, 3) rotation matrix → (4,) unit quaternion (w, x, y, z), w ≥ 0: COLMAP's order."""
    return np.roll(rotation_to_quaternion(np.asarray(rotation, np.float64)[None])[0], 1)


def rotation_from_wxyz(q: np.ndarray) -> np.ndarray:
    """(4,) quaternion (w, x, y, z) → (3, 3) rotation matrix."""
    w, x, y, z = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


class ColmapImage(NamedTuple):
    """One keyframe as a COLMAP image."""

    name: str  # image file name
    world_from_cam: np.ndarray  # (4, 4) float64
    intrinsics: np.ndarray  # (4,) float64 (fx, fy, cx, cy), our pixel convention
    size: tuple[int, int]  # (width, height) in pixels


class ColmapWriter:
    """cameras.txt (one PINHOLE camera per keyframe), images.txt (cam_from_world), empty points3D.txt, written
    as cameras are added (in keyframe order), so an export of any length holds one camera at a time."""

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self._cams = open(self.folder / "cameras.txt", "w")
        self._imgs = open(self.folder / "images.txt", "w")
        self._cams.write("# Camera list with one line of data per camera:\n"
                         "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n")
        self._imgs.write("# Image list with two lines of data per image:\n"
                         "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
                         "#   POINTS2D[] as (X, Y, POINT3D_ID)\n")
        self.count = 0

    def add(self, im: ColmapImage) -> None:
        self.count += 1
        image_id = self.count
        fx, fy, cx, cy = (float(v) for v in im.intrinsics)
        self._cams.write(f"{image_id} PINHOLE {im.size[0]} {im.size[1]} {fx!r} {fy!r} {cx + 0.5!r} {cy + 0.5!r}\n")
        cam_from_world = np.linalg.inv(im.world_from_cam)
        q = quaternion_wxyz(cam_from_world[:3, :3])
        t = cam_from_world[:3, 3]
        pose_text = " ".join(repr(float(v)) for v in (*q, *t))
        self._imgs.write(f"{image_id} {pose_text} {image_id} {im.name}\n\n")

    def close(self) -> Path:
        self._cams.close()
        self._imgs.close()
        (self.folder / "points3D.txt").write_text("# 3D point list (empty: the dense map is in map.ply)\n")
        return self.folder


def write_colmap(folder: Path, images: dict[int, ColmapImage]) -> Path:
    """cameras.txt (one PINHOLE camera per keyframe), images.txt (cam_from_world), empty points3D.txt."""
    writer = ColmapWriter(folder)
    for kf_id in sorted(images):
        writer.add(images[kf_id])
    return writer.close()


def read_colmap(folder: Path) -> dict[str, ColmapImage]:
    """Read cameras.txt + images.txt written by any COLMAP tool (PINHOLE cameras) back into our conventions."""
    folder = Path(folder)
    cams = {}
    for line in (folder / "cameras.txt").read_text().splitlines():
        if line and not line.startswith("#"):
            cid, model, w, h, *params = line.split()
            if model != "PINHOLE":
                raise ValueError(f"camera {cid}: only PINHOLE is supported, got {model}")
            fx, fy, cx, cy = map(float, params)
            cams[cid] = (np.array([fx, fy, cx - 0.5, cy - 0.5]), (int(w), int(h)))
    out = {}
    lines = [x for x in (folder / "images.txt").read_text().splitlines() if not x.startswith("#")]
    for line in lines[::2]:
        _, *vals, cid, name = line.split()
        cam_from_world = np.eye(4)
        cam_from_world[:3, :3] = rotation_from_wxyz(np.array(vals[:4], float))
        cam_from_world[:3, 3] = np.array(vals[4:7], float)
        out[name] = ColmapImage(name, np.linalg.inv(cam_from_world), *cams[cid])
    return out


# ----- everything at once --------------------------------------------------------------------------
class ExportResult(NamedTuple):
    """Paths written by `export_all`."""

    ply: Path
    depth_maps: list[Path]
    colmap: Path
    images: list[Path]


def export_all(out: Path, xyz: np.ndarray, rgb: np.ndarray, depths: dict[int, KeyframeDepth],
               cameras: dict[int, ColmapImage], metric: bool, jpegs: dict[int, bytes] | None = None,
               label_rgb: np.ndarray | None = None) -> ExportResult:
    """Write `map.ply`, `depth/`, `colmap/` (cameras.txt, images.txt, points3D.txt) and `images/`.

    Args:
        out: output folder.
        xyz, rgb, label_rgb: the fused map points, (N, 3) float / uint8 / uint8.
        depths: latest geometry per keyframe; cameras: pose, intrinsics and image name per keyframe.
        metric: depth maps as 16-bit PNG mm (True) or npz (scale-free map).
        jpegs: keyframe images (written to images/ under their camera name).
    """
    writer = ExportWriter(out, xyz, rgb, metric, label_rgb)
    for kf_id in sorted(depths):
        writer.add_depth(kf_id, depths[kf_id])
    for kf_id in sorted(cameras):
        writer.add_camera(cameras[kf_id], (jpegs or {}).get(kf_id))
    return writer.close()


class ExportWriter:
    """`export_all` one keyframe at a time (ascending ids): the point cloud at once, then each keyframe's depth
    map, camera and image as it is added, so an export holds one keyframe at a time."""

    def __init__(self, out: Path, xyz: np.ndarray, rgb: np.ndarray, metric: bool,
                 label_rgb: np.ndarray | None = None) -> None:
        self.out = Path(out)
        self.metric = metric
        self.n_points = len(xyz)
        self.ply = write_ply(self.out / "map.ply", xyz, rgb, label_rgb)
        (self.out / "depth").mkdir(parents=True, exist_ok=True)
        self.colmap = ColmapWriter(self.out / "colmap")
        self.depth_paths: list[Path] = []
        self.image_paths: list[Path] = []

    def add_depth(self, kf_id: int, depth: KeyframeDepth) -> None:
        self.depth_paths += write_depth_maps(self.out / "depth", {kf_id: depth}, self.metric)

    def add_camera(self, camera: ColmapImage, jpeg: bytes | None = None) -> None:
        self.colmap.add(camera)
        if jpeg is not None:
            path = self.out / "images" / camera.name
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(jpeg)
            self.image_paths.append(path)

    def add(self, kf_id: int, depth: KeyframeDepth, camera: ColmapImage | None, jpeg: bytes | None = None) -> None:
        """A keyframe's depth map and, unless None (an invalid pose), its camera and image."""
        self.add_depth(kf_id, depth)
        if camera is not None:
            self.add_camera(camera, jpeg)

    def close(self) -> ExportResult:
        colmap = self.colmap.close()
        log.info("exported %d points, %d depth maps, %d cameras to %s", self.n_points, len(self.depth_paths),
                 self.colmap.count, self.out)
        return ExportResult(self.ply, self.depth_paths, colmap, self.image_paths)
