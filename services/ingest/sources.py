"""Video sources: each yields frames in order as :class:`SourceFrame` (or :class:`BadFrame` for a frame that
could not be read — the stream goes on). ``open_source(spec)`` picks the right one or raises SourceError
with a message that says how to fix it. ROS 2 sources (a ``ros2:`` topic, a bag) are read by
:mod:`services.ros2.sources`, imported only when asked for.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Protocol

import cv2
import numpy as np

from ..common.errors import ConfigError, SourceError

log = logging.getLogger(__name__)

VIDEO_SUFFIXES = {".mp4", ".avi", ".mkv", ".mov", ".webm", ".m4v"}
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm"}
TUM_DEPTH_SCALE = 5000.0  # TUM RGB-D depth PNGs: 16-bit, 5000 units per metre
ADT_DEPTH_SCALE = 1000.0  # Aria Digital Twin depth PNGs: 16-bit millimetres (z-depth)
MAX_CONSECUTIVE_FAILURES = 25  # a video that fails this many reads in a row has ended
ROS_TOPIC_PREFIX = "ros2:"  # ros2:/camera/image_raw: a live ROS 2 image topic over Zenoh
BAG_SUFFIXES = {".mcap", ".db3"}  # rosbag2 storage files


@dataclass(frozen=True)
class SourceFrame:
    index: int  # position in the source (0-based, before stride)
    t_ns: int
    rgb: np.ndarray  # (H, W, 3) uint8 RGB
    depth: np.ndarray | None = None  # (H, W) float32 metres, 0 = missing


@dataclass(frozen=True)
class BadFrame:
    index: int
    reason: str


class Source(Protocol):
    name: str
    fps: float | None  # native rate of a recorded source; None for live ones
    live: bool

    def frames(self) -> Iterator[SourceFrame | BadFrame]: ...


def _bgr_to_rgb(image: np.ndarray) -> np.ndarray:
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


class CaptureSource:
    """Anything OpenCV's VideoCapture opens: a video file, a V4L2 camera, an RTSP/HTTP stream."""

    def __init__(self, target: str | int, name: str, live: bool):
        self.name, self.live = name, live
        self._capture = cv2.VideoCapture(target)
        if not self._capture.isOpened():
            hint = {
                True: "check the camera index with `ls /dev/video*` (and that no other program holds it), or the URL",
                False: "check the path and that the file is a video OpenCV/FFmpeg can decode",
            }[live]
            raise SourceError(f"cannot open video source {name!r}: {hint}")
        fps = self._capture.get(cv2.CAP_PROP_FPS)
        self.fps = None if live or not fps or fps > 1000 else float(fps)
        self._count = int(self._capture.get(cv2.CAP_PROP_FRAME_COUNT)) if not live else 0

    def frames(self) -> Iterator[SourceFrame | BadFrame]:
        index, failures, start = 0, 0, time.monotonic_ns()
        try:
            while failures < MAX_CONSECUTIVE_FAILURES:
                ok, image = self._capture.read()
                if ok and image is not None and image.size:
                    failures = 0
                    t_ns = int(index * 1e9 / self.fps) if self.fps else time.monotonic_ns() - start
                    yield SourceFrame(index, t_ns, _bgr_to_rgb(image))
                elif not self.live and index >= self._count:
                    return
                else:
                    failures += 1
                    yield BadFrame(index, "decoder returned no image")
                index += 1
        finally:
            self._capture.release()


@dataclass(frozen=True)
class _Entry:
    t_ns: int
    path: Path
    depth_path: Path | None = None


def _read_list(path: Path) -> list[tuple[float, str]]:
    """A TUM-style list: ``timestamp filename`` lines, ``#`` comments."""
    rows = []
    for line in path.read_text().splitlines():
        parts = line.split()
        if parts and not parts[0].startswith("#") and len(parts) >= 2:
            rows.append((float(parts[0]), parts[1]))
    return rows


def _associate(rgb: list[tuple[float, str]], depth: list[tuple[float, str]], max_dt: float) -> dict[str, str]:
    """Nearest depth stamp for each rgb stamp within ``max_dt`` seconds."""
    if not depth:
        return {}
    stamps = np.array([t for t, _ in depth])
    found = {}
    for t, name in rgb:
        k = int(np.argmin(np.abs(stamps - t)))
        if abs(stamps[k] - t) <= max_dt:
            found[name] = depth[k][1]
    return found


class ImageFolderSource:
    """A folder of images: TUM RGB-D layout (``rgb.txt`` [+ ``depth.txt``]), KITTI odometry (``image_0/`` or
    ``image_2/`` + ``times.txt``), or plain sorted image files."""

    live = False

    def __init__(self, root: Path, fps: float | None = None, use_depth: bool = False,
                 depth_scale: float | None = None):
        """``use_depth``: read the sensor depth a ``depth.txt`` lists (off by default: a depth file lying in a
        folder is no request to use it); ``depth_scale``: depth PNG units per metre, default per dataset
        (:func:`depth_units`)."""
        self.name = str(root)
        self.entries = self._scan(root, use_depth)
        self.depth_scale = depth_units(root) if depth_scale is None else float(depth_scale)
        if not self.depth_scale > 0:
            raise SourceError(f"depth scale must be > 0 units per metre, got {self.depth_scale}")
        if not self.entries:
            raise SourceError(f"no images found in {root} (looked for rgb.txt, image_0/, image_2/ and image files)")
        if fps:
            self.fps = fps
        elif len(self.entries) > 1:
            span = (self.entries[-1].t_ns - self.entries[0].t_ns) / 1e9
            self.fps = (len(self.entries) - 1) / span if span > 0 else 10.0
        else:
            self.fps = 10.0

    @staticmethod
    def _scan(root: Path, use_depth: bool) -> list[_Entry]:
        if (root / "rgb.txt").is_file():
            rgb = _read_list(root / "rgb.txt")
            depth = _read_list(root / "depth.txt") if use_depth and (root / "depth.txt").is_file() else []
            pairs = _associate(rgb, depth, max_dt=0.02)
            return [
                _Entry(int(round(t * 1e9)), root / name, root / pairs[name] if name in pairs else None) for t, name in rgb
            ]
        for sub in ("image_0", "image_2"):
            if (root / sub).is_dir():
                files = sorted(p for p in (root / sub).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
                times = root / "times.txt"
                stamps = [float(x) for x in times.read_text().split()] if times.is_file() else []
                if len(stamps) != len(files):
                    stamps = [i / 10.0 for i in range(len(files))]  # KITTI runs at 10 Hz
                return [_Entry(int(round(t * 1e9)), p) for t, p in zip(stamps, files)]
        files = sorted(p for p in root.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        return [_Entry(int(i * 1e8), p) for i, p in enumerate(files)]

    def frames(self) -> Iterator[SourceFrame | BadFrame]:
        for index, entry in enumerate(self.entries):
            image = cv2.imread(str(entry.path), cv2.IMREAD_COLOR)
            if image is None:
                yield BadFrame(index, f"unreadable image {entry.path.name}")
                continue
            depth = None
            if entry.depth_path is not None:
                raw = cv2.imread(str(entry.depth_path), cv2.IMREAD_UNCHANGED)
                if raw is not None and raw.shape[:2] == image.shape[:2]:
                    depth = raw.astype(np.float32) / self.depth_scale
                else:
                    log.warning("depth image unreadable or of another size; frame sent without depth",
                                extra={"seq": index, "path": str(entry.depth_path)})
            yield SourceFrame(index, entry.t_ns, _bgr_to_rgb(image), depth)


def depth_units(root: Path) -> float:
    """Depth PNG units per metre of an image folder: millimetres for an Aria Digital Twin extraction (it keeps
    ADT's ``camera_rgb_calibration.json``), else TUM RGB-D's 5000 (the layout ``depth.txt`` comes from)."""
    if (root / "camera_rgb_calibration.json").is_file():
        return ADT_DEPTH_SCALE
    return TUM_DEPTH_SCALE


class RosSource:
    """ROS 2 images (services/ros2/sources.py): a live topic over Zenoh (``ros2:/camera/image_raw``) or one topic
    of a recorded bag; each frame stamped with its message's header stamp."""

    def __init__(self, images, name: str, live: bool, fps: float | None = None):
        self._images, self.name, self.live, self.fps = images, name, live, fps

    def frames(self) -> Iterator[SourceFrame | BadFrame]:
        from ..ros2.sources import RosImageError

        for item in self._images.images():
            if isinstance(item, RosImageError):
                yield BadFrame(item.index, item.reason)
            else:
                yield SourceFrame(item.index, item.t_ns, item.rgb)


def _ros_topic(spec: str) -> RosSource:
    from ..ros2.config import Ros2Settings, RosZenohSettings
    from ..ros2.sources import TopicImages

    topic = spec[len(ROS_TOPIC_PREFIX):]
    return RosSource(TopicImages(topic, Ros2Settings(), RosZenohSettings()), spec, live=True)


def _ros_bag(path: Path, topic: str) -> RosSource:
    from ..ros2.sources import BagImages

    bag = BagImages(path, topic)
    return RosSource(bag, f"{path}:{bag.topic}", live=False, fps=bag.fps)


def is_ros_bag(path: Path) -> bool:
    """A rosbag2 recording: one ``.mcap`` / ``.db3`` file, or a folder holding ``metadata.yaml``."""
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    return path.is_file() and path.suffix.lower() in BAG_SUFFIXES


def open_source(spec: str, fps: float | None = None, use_depth: bool = False,
                depth_scale: float | None = None, topic: str = "") -> Source:
    """Open a source from its spec (see IngestSettings.source); ``use_depth`` / ``depth_scale``: sensor depth of
    an image folder (see :class:`ImageFolderSource`); ``topic``: the image topic of a ROS 2 bag."""
    if not spec:
        raise SourceError("no source given: pass a video file, image folder, camera index, URL, ROS 2 bag, "
                          "ros2:/TOPIC or synth:")
    if spec.startswith(ROS_TOPIC_PREFIX):
        return _ros_topic(spec)
    if spec.startswith("synth:"):
        from ..synth.spec import spec_options
        from .synth_source import SynthSource  # the renderer is only loaded when asked for

        try:
            options = spec_options(spec)
        except ConfigError as exc:
            raise SourceError(str(exc)) from exc
        return SynthSource(**options)
    if spec.isdigit() or spec.startswith("/dev/video"):
        return CaptureSource(int(spec) if spec.isdigit() else spec, spec, live=True)
    if "://" in spec:
        return CaptureSource(spec, spec, live=True)
    path = Path(spec).expanduser()
    if is_ros_bag(path):
        return _ros_bag(path, topic)
    if path.is_dir():
        return ImageFolderSource(path, fps=fps, use_depth=use_depth, depth_scale=depth_scale)
    if path.is_file():
        if path.suffix.lower() not in VIDEO_SUFFIXES:
            log.warning("unknown video suffix; trying OpenCV anyway", extra={"path": str(path)})
        return CaptureSource(str(path), str(path), live=False)
    raise SourceError(f"source {spec!r} not found: no such file or folder")
