"""The COLMAP model of the map (``colmap/``, text and binary), written the way COLMAP reads it.

It has one shared PINHOLE camera (a stream has one refined set of
intrinsics, the newest keyframe's; fy keeps its ratio to fx, so PINHOLE, not SIMPLE_PINHOLE), one image per
keyframe (cam_from_world as qw qx qy qz, t) and the map points as points3D, each with the keyframes that see it
as its track: a point is in a keyframe's track where it projects inside the image and agrees with that
keyframe's depth there (a point behind what the keyframe sees is occluded, one in front of it is not there in
that view). POINT3D_ID is the point's row in map.ply + 1. COLMAP puts pixel centres at +0.5 (the image spans
[0, W]); ours are at integers (docs/CONVENTIONS.md), so principal points and 2D points gain 0.5 on the way out.
The files are written here, not by pycolmap: their layouts are a few documented records, and pycolmap (COLMAP
compiled) would be a large runtime dependency of the mapstore; tests/test_colmap_export.py reads them with it.
Both files are streamed as they are formatted: images a record at a time, points3D a batch of points at a time
(its binary records interleaved by index arithmetic), and the text's numbers a batch at a time
(:mod:`services.common.number_text`): a long stream's model holds ~5 M observations, 9 s of `repr` and ~200 MB
of text held whole before, and a record per point was ~25 µs of Python. The points an image sees are found on a
thread of the writer while the export reads the next keyframe, and images and points3D are written side by side:
mostly numpy, so each leaves the GIL to the other (the 10,000-frame map's export 3.4 -> 2.7 s). 2D points are
written to 1e-6 px, the same in the text and the binary model.
"""

from __future__ import annotations

import logging
import struct
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator, NamedTuple

import numpy as np
from services.common.number_text import format_rows
from services.common.rotations import quaternion_wxyz, rotation_from_wxyz
from services.mapstore.core.geometry import grid_intrinsics, project, transform_points
from services.mapstore.core.keyframe import KeyframeDepth

log = logging.getLogger(__name__)

@dataclass(frozen=True)
class ColmapParams:
    """Which map points the COLMAP model carries, and in which images."""

    rel_depth_tolerance: float = 0.05
    """A keyframe sees a point when |z_point − z_keyframe| ≤ this · z_keyframe at the point's grid cell (the map's
    own multi-view check uses the same 5 %: ConsistencyParams.rel_tolerance)."""
    max_points_per_image: int = 2048
    """At most this many observations per image. Every image keeps the visible points that come first in one
    fixed random order of the map, so the images that share points keep the same ones and tracks stay long. A
    10,000-frame stream's model at 4096 held 4.9 M observations and was most of the end of stream's export
    (bench/export.py: 5.2 s at 4096, 3.3 s at 2048); COLMAP's own reconstructions keep a few hundred to a few
    thousand per image, and the dense map is map.ply."""
    min_track_length: int = 2
    """Points seen by fewer keyframes are left out (one view does not constrain a point)."""
    seed: int = 0
    """Seeds that order."""


class ColmapImage(NamedTuple):
    """One keyframe as a COLMAP image."""

    name: str  # image file name
    world_from_cam: np.ndarray  # (4, 4) float64
    intrinsics: np.ndarray  # (4,) float64 (fx, fy, cx, cy), our pixel convention
    size: tuple[int, int]  # (width, height) in pixels


def visible_points(points_world: np.ndarray, cam_from_world: np.ndarray, depth: KeyframeDepth,
                   rel_tolerance: float) -> np.ndarray:
    """Indices (M,) int64, ascending, of the points (N, 3) a keyframe sees: in front of it, inside its grid and
    within ``rel_tolerance`` of its depth (``depth.disparity`` (h, w), 0 = unknown) at the cell they land on —
    the nearest cell, as the map's own multi-view check (core/consistency.py) reads it. (Interpolating the 2x2
    cells around the point instead gave 1 % fewer wrong observations at depth edges and 5 % fewer right ones on
    the synthetic room of tests/test_colmap_export.py.)"""
    h, w = depth.disparity.shape
    fx, fy, cx, cy = grid_intrinsics(depth.intrinsics)
    # x, y, z as rows: a (3, 3) @ (3, N) product is twice as fast as (N, 3) @ (3, 3) here (most of the export)
    x, y, z = cam_from_world[:3, :3] @ np.asarray(points_world, np.float64).T + cam_from_world[:3, 3:]
    safe = np.where(z > 0, z, np.nan)  # NaN behind the camera: every comparison below is False
    col, row = np.rint(x / safe * fx + cx), np.rint(y / safe * fy + cy)
    idx = np.flatnonzero((z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h))
    disp = depth.disparity[row[idx].astype(np.int64), col[idx].astype(np.int64)].astype(np.float64)
    z_kf = 1.0 / np.where(disp > 0, disp, np.inf)
    return idx[(disp > 0) & (np.abs(z[idx] - z_kf) <= rel_tolerance * z_kf)]


_CAMERA_BIN = struct.Struct("<iiQQ")  # camera_id, model_id, width, height (then the params as doubles)
_IMAGE_BIN = struct.Struct("<i4d3di")  # image_id, qw qx qy qz, tx ty tz, camera_id (then name\0, points2D)
_POINT2D_BIN = np.dtype([("x", "<f8"), ("y", "<f8"), ("point3D_id", "<i8")])
_POINT3D_BIN = np.dtype([("id", "<u8"), ("xyz", "<f8", 3), ("rgb", "u1", 3), ("error", "<f8"), ("length", "<u8")])
_TRACK_BIN = np.dtype([("image_id", "<i4"), ("point2D_idx", "<i4")])
PINHOLE_MODEL_ID = 1
POINT2D_DECIMALS = 6  # 2D points in pixels to 1e-6 px, in the text and the binary model alike


class ColmapWriter:
    """A COLMAP model written in both formats (cameras/images/points3D .txt and .bin) as keyframes are added in
    order: an image keeps its pose and the ids of the map points it sees, the model is written on close."""

    def __init__(self, folder: Path, xyz: np.ndarray | None = None, rgb: np.ndarray | None = None,
                 params: ColmapParams | None = None) -> None:
        """``xyz`` (N, 3) float, ``rgb`` (N, 3) uint8: the map points (none: images without points)."""
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.params = params or ColmapParams()
        self.xyz = np.zeros((0, 3)) if xyz is None else np.asarray(xyz)
        self.rgb = np.zeros((len(self.xyz), 3), np.uint8) if rgb is None else np.asarray(rgb, np.uint8)
        rank = np.random.default_rng(self.params.seed).permutation(len(self.xyz))  # each point's place in the cap's
        self._order = np.argsort(rank)  # fixed order; the point ids in that order, and their xyz
        self._xyz_in_order = np.ascontiguousarray(self.xyz[self._order])
        self._images: list[tuple[ColmapImage, Future]] = []  # each image and the ids of the points it sees
        # an image's points are found on this thread while the caller reads the next keyframe (mostly numpy on
        # both, which leaves the GIL to the other)
        self._finder = ThreadPoolExecutor(1, thread_name_prefix="colmap-visible")

    @property
    def count(self) -> int:
        return len(self._images)

    def add(self, im: ColmapImage, depth: KeyframeDepth | None = None) -> None:
        """A keyframe's image; the map points it sees when its ``depth`` is given. An image of another size than
        the first cannot share its camera: it is left out (logged), not the export."""
        if self._images and tuple(im.size) != tuple(self._images[0][0].size):
            log.warning("image of another size left out of the COLMAP model",
                        extra={"image": im.name, "size": im.size, "camera_size": self._images[0][0].size})
            return
        self._images.append((im, self._finder.submit(self._first_visible, im.world_from_cam, depth)))

    def _first_visible(self, world_from_cam: np.ndarray, depth: KeyframeDepth | None) -> np.ndarray:
        """The (at most ``max_points_per_image``) visible points that come first in the fixed order, ascending (none
        without a ``depth``). The points are tested in that order, a growing chunk at a time, until the cap is
        reached: a keyframe that sees a share f of the map tests ~cap / f points, not the map (bench/export.py, 1203
        keyframes x 312k points: 13.8 s -> 2.3 s)."""
        if depth is None:
            return np.zeros(0, np.int64)
        cam_from_world = np.linalg.inv(world_from_cam)
        cap = self.params.max_points_per_image
        start, chunk, found, count = 0, 8 * cap, [np.zeros(0, np.int64)], 0
        while start < len(self._order) and count < cap:
            end = start + chunk
            found.append(self._order[start:end][visible_points(self._xyz_in_order[start:end], cam_from_world, depth,
                                                               self.params.rel_depth_tolerance)])
            count += len(found[-1])
            start, chunk = end, 2 * chunk
        return np.sort(np.concatenate(found)[:cap])

    def close(self) -> Path:
        """Write the model; a folder without images gets empty files."""
        try:
            self._images = [(im, seen.result()) for im, seen in self._images]
        finally:
            self._finder.shutdown(cancel_futures=True)
        intrinsics = np.asarray(self._images[-1][0].intrinsics, np.float64) if self._images else None
        tracked = self._tracked()
        cam_from_world = [np.linalg.inv(im.world_from_cam) for im, _ in self._images]
        points2d = [self._points2d(intrinsics, pose, seen[tracked[seen]])
                    for (_, seen), pose in zip(self._images, cam_from_world)]
        tracks = self._tracks(points2d)
        self._write_cameras(intrinsics)
        # images and points3D side by side: their formatting is mostly numpy, which lets the other run meanwhile
        with ThreadPoolExecutor(1) as pool:
            points = pool.submit(self._write_points, tracks)
            self._write_images(cam_from_world, points2d)
            points.result()
        log.info("COLMAP model written", extra={"folder": str(self.folder), "images": self.count,
                                                "points3D": len(tracks[0]), "observations": len(tracks[1])})
        return self.folder

    def _tracked(self) -> np.ndarray:
        seen = [s for _, s in self._images]
        views = np.bincount(np.concatenate(seen), minlength=len(self.xyz)) if seen else np.zeros(len(self.xyz))
        return views >= self.params.min_track_length

    def _points2d(self, intrinsics: np.ndarray, cam_from_world: np.ndarray, ids: np.ndarray) -> np.ndarray:
        proj = project(transform_points(cam_from_world, self.xyz[ids]), intrinsics)
        out = np.empty(len(ids), _POINT2D_BIN)
        # rounded as the text writes them, so images.txt and images.bin hold the same numbers
        out["x"], out["y"] = np.round(proj.u + 0.5, POINT2D_DECIMALS), np.round(proj.v + 0.5, POINT2D_DECIMALS)
        out["point3D_id"] = ids + 1
        return out

    def _tracks(self, points2d: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(point ids (P,), track elements (T,) of _TRACK_BIN grouped by point, start of each point's elements)."""
        ids = np.concatenate([p["point3D_id"] for p in points2d] + [np.zeros(0, np.int64)])
        elements = np.empty(len(ids), _TRACK_BIN)
        elements["image_id"] = np.repeat(np.arange(1, len(points2d) + 1), [len(p) for p in points2d])
        elements["point2D_idx"] = np.concatenate([np.arange(len(p)) for p in points2d] + [np.zeros(0, np.int64)])
        order = np.argsort(ids, kind="stable")  # by point, then by image
        sorted_ids = ids[order]
        starts = np.flatnonzero(np.diff(sorted_ids, prepend=-1))  # sorted already: np.unique would sort again
        return sorted_ids[starts], elements[order], starts

    def _write_cameras(self, k: np.ndarray | None) -> None:
        records = []
        if k is not None:
            width, height = self._images[0][0].size
            params = (k[0], k[1], k[2] + 0.5, k[3] + 0.5)
            records.append((f"1 PINHOLE {width} {height} {' '.join(repr(float(v)) for v in params)}".encode(),
                            _CAMERA_BIN.pack(1, PINHOLE_MODEL_ID, width, height) + struct.pack("<4d", *params)))
        self._write("cameras", ["Camera list with one line of data per camera:", "  CAMERA_ID, MODEL, WIDTH, "
                                "HEIGHT, PARAMS[]", f"Number of cameras: {len(records)}"], len(records), records)

    def _write_images(self, cam_from_world: list[np.ndarray], points2d: list[np.ndarray]) -> None:
        def records() -> Iterator[tuple[bytes, bytes]]:
            observations = _grouped_lines(points2d, ("x", "y", "point3D_id"), (POINT2D_DECIMALS, POINT2D_DECIMALS, 0))
            poses = np.reshape(cam_from_world, (-1, 4, 4))
            # every image's rotation at once: one at a time, scipy's conversion was 7 % of a long stream's export
            values = np.concatenate([quaternion_wxyz(poses[:, :3, :3]), poses[:, :3, 3]], axis=1).tolist()
            for image_id, ((im, _), pose_values, obs, obs_line) in enumerate(zip(self._images, values, points2d,
                                                                                  observations), start=1):
                line = f"{image_id} {' '.join(repr(float(v)) for v in pose_values)} 1 {im.name}\n".encode()
                yield line + obs_line, b"".join([_IMAGE_BIN.pack(image_id, *pose_values, 1), im.name.encode() + b"\0",
                                                 struct.pack("<Q", len(obs)), obs.tobytes()])

        mean = sum(len(p) for p in points2d) / max(self.count, 1)
        self._write("images", ["Image list with two lines of data per image:", "  IMAGE_ID, QW, QX, QY, QZ, TX, TY, "
                               "TZ, CAMERA_ID, NAME", "  POINTS2D[] as (X, Y, POINT3D_ID)",
                               f"Number of images: {self.count}, mean observations per image: {mean:g}"],
                    self.count, records())

    def _write_points(self, tracks: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
        point_ids, elements, starts = tracks
        rows = np.empty(len(point_ids), _POINT3D_BIN)
        rows["id"], rows["xyz"], rows["rgb"] = point_ids, self.xyz[point_ids - 1], self.rgb[point_ids - 1]
        rows["error"] = 0.0  # the 2D points are these points' projections: no reprojection error by construction
        rows["length"] = np.diff(np.append(starts, len(elements)))
        bounds = np.append(starts, len(elements))

        def records() -> Iterator[tuple[bytes, bytes]]:
            # a batch of points at a time: a long stream's model has ~10^5 points, and a record per point cost
            # ~25 µs of Python each (bench/export.py)
            for first, last in _batches(rows["length"], TRACK_BATCH // 4):  # the binary's byte indices: ~20 MB
                batch, a, b = rows[first:last], int(bounds[first]), int(bounds[last])
                track = elements[a:b]
                text, offsets = format_rows([track["image_id"], track["point2D_idx"]], (0, 0))
                ends = offsets[bounds[first:last + 1] - a].tolist()
                # xyz as repr: the shortest text that reads back as the binary's double
                heads = [f"{pid} {x!r} {y!r} {z!r} {r} {g} {b_} 0 ".encode() for pid, (x, y, z), (r, g, b_)
                         in zip(batch["id"].tolist(), batch["xyz"].tolist(), batch["rgb"].tolist())]
                lines = b"\n".join(head + text[begin:end - 1] for head, begin, end in zip(heads, ends[:-1], ends[1:]))
                yield lines, _interleaved(batch, track)

        mean = len(elements) / max(len(point_ids), 1)
        self._write("points3D", ["3D point list with one line of data per point:", "  POINT3D_ID, X, Y, Z, R, G, B, "
                                 "ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
                                 f"Number of points: {len(point_ids)}, mean track length: {mean:g}"],
                    len(point_ids), records())

    def _write(self, name: str, comments: list[str], count: int, records: Iterable[tuple[bytes, bytes]]) -> None:
        """``name``.txt and .bin from ``count`` records of (text line, binary record), written as they come: a
        long stream's model is ~200 MB of text that need not be held whole."""
        with open(self.folder / f"{name}.txt", "wb") as text, open(self.folder / f"{name}.bin", "wb") as binary:
            text.write("".join(f"# {c}\n" for c in comments).encode())
            binary.write(struct.pack("<Q", count))
            for line, record in records:
                text.write(line)
                text.write(b"\n")
                binary.write(record)


TRACK_BATCH = 1 << 18
"""Track elements (or 2D points) formatted at once: a long stream's model holds ~5 M."""


def _batches(lengths: np.ndarray, max_rows: int) -> Iterator[tuple[int, int]]:
    """Consecutive [first, last) ranges of groups of ``lengths`` rows, each of at most ``max_rows`` rows (or one
    group, when a group alone has more)."""
    ends = np.cumsum(lengths)
    first = 0
    while first < len(lengths):
        before = int(ends[first - 1]) if first else 0
        last = max(first + 1, int(np.searchsorted(ends, before + max_rows, side="right")))
        yield first, last
        first = last


def _interleaved(rows: np.ndarray, elements: np.ndarray) -> bytes:
    """The binary records of points3D.bin for ``rows`` (_POINT3D_BIN, their ``length`` elements each) and their
    track ``elements`` (_TRACK_BIN, grouped by point): each row followed by its elements."""
    row_size, element_size = rows.dtype.itemsize, elements.dtype.itemsize
    lengths = rows["length"].astype(np.int64)
    out = np.empty(len(rows) * row_size + len(elements) * element_size, np.uint8)
    # row i is preceded by i rows and the elements of points before it; element j by j elements and the rows of
    # its own point and those before
    elements_before = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    row_at = np.arange(len(rows)) * row_size + elements_before * element_size
    element_at = np.repeat(np.arange(1, len(rows) + 1) * row_size, lengths) + np.arange(len(elements)) * element_size
    out[(row_at[:, None] + np.arange(row_size)).ravel()] = rows.view(np.uint8)
    out[(element_at[:, None] + np.arange(element_size)).ravel()] = elements.view(np.uint8)
    return out.tobytes()


def _grouped_lines(groups: list[np.ndarray], fields: tuple[str, ...], decimals: tuple[int, ...],
                   batch_rows: int = TRACK_BATCH) -> Iterator[bytes]:
    """Each group's rows (a structured array) as one line of text, its ``fields`` separated by spaces: formatted
    a batch of groups at a time (:func:`format_rows`; a long stream's model holds ~5 M rows, so at most
    ``batch_rows`` of their characters exist at once)."""
    lengths = np.array([len(g) for g in groups], np.int64)
    for first, last in _batches(lengths, batch_rows):
        batch = np.concatenate(groups[first:last])
        text, offsets = format_rows([batch[f] for f in fields], decimals)
        bounds = offsets[np.concatenate([[0], np.cumsum(lengths[first:last])])].tolist()
        for begin, end in zip(bounds[:-1], bounds[1:]):
            yield text[begin:max(begin, end - 1)]


def write_colmap(folder: Path, images: dict[int, ColmapImage], xyz: np.ndarray | None = None,
                 rgb: np.ndarray | None = None, depths: dict[int, KeyframeDepth] | None = None,
                 params: ColmapParams | None = None) -> Path:
    """A COLMAP model (text and binary) of keyframe ``images``; with the map points ``xyz``/``rgb`` and the
    keyframes' ``depths``, the points each keyframe sees become its 2D points and the points' tracks."""
    writer = ColmapWriter(folder, xyz, rgb, params)
    for kf_id in sorted(images):
        writer.add(images[kf_id], (depths or {}).get(kf_id))
    return writer.close()


def read_colmap(folder: Path) -> dict[str, ColmapImage]:
    """Read cameras.txt + images.txt written by any COLMAP tool (PINHOLE or SIMPLE_PINHOLE cameras) back into our
    conventions (points are not read)."""
    folder = Path(folder)
    cams = {}
    for line in (folder / "cameras.txt").read_text().splitlines():
        if line and not line.startswith("#"):
            cid, model, w, h, *params = line.split()
            if model not in ("PINHOLE", "SIMPLE_PINHOLE"):
                raise ValueError(f"camera {cid}: only PINHOLE and SIMPLE_PINHOLE are supported, got {model}")
            fx, fy, cx, cy = map(float, params if model == "PINHOLE" else params[:1] + params)
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
