"""What a run looks like in Rerun (https://rerun.io): each KM-ViPE message or answer as ``(entity path, archetype)``
pairs, and the recorder's settings. Pure: messages and arrays in, archetypes out, no bus and no file; the bus side
is :mod:`services.runner.rerun_recorder`.

Entities (timeline ``frame`` = the frame's ``seq``; poses are ``world_from_cam``, camera x right, y down, z forward):

- ``world``: view coordinates RDF (static), so the first camera looks into the screen with image-up up.
- ``world/camera``: the ``Transform3D`` of every posed frame; a pose mapping revises is logged again at its frame.
- ``world/camera/image``: the ``Pinhole`` (the latest intrinsics, scaled to the frame; drawn as the frustum) and
  every Nth frame's image (the JPEG as sent, not decoded), and its sensor depth when the source sends one.
- ``world/trajectory``: ``LineStrips3D`` of the camera centres in frame order; ``world/keyframes``: ``Points3D`` of
  the keyframes' centres.
- ``world/map``: ``Points3D`` of the fused map (the mapstore's export), refreshed while streaming and at the end.
- ``world/queries/<text>``: ``Boxes3D`` of the regions the gateway answered for ``<text>``, and under ``points``
  their best points.

rerun-sdk is optional: :func:`load_rerun` imports it on first use and says what to install when it is missing.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from ..common import camera
from ..common.errors import ConfigError
from ..common.schema import Frame

RERUN_REQUIREMENT = "rerun-sdk>=0.41"
RERUN_INSTALL = f"pip install '{RERUN_REQUIREMENT}'"
VIEWER_SCHEMES = ("rerun://", "rerun+http://", "rerun+https://")
DEFAULT_VIEWER = "rerun+http://127.0.0.1:9876/proxy"  # what `rerun` (the viewer) listens on by default
TIMELINE = "frame"

WORLD = "world"
CAMERA = "world/camera"
IMAGE = "world/camera/image"
DEPTH = "world/camera/image/depth"
TRAJECTORY = "world/trajectory"
KEYFRAMES = "world/keyframes"
MAP = "world/map"
QUERIES = "world/queries"

HIGHLIGHT = (255, 40, 200)  # query answers: a colour no synthetic or natural scene is made of
KEYFRAME_COLOUR = (255, 170, 0)
TRAJECTORY_COLOUR = (40, 120, 255)

Entity = tuple[str, Any]  # (entity path, a rerun archetype)


@dataclass(frozen=True)
class RerunSettings:
    """Where a run's recording goes and what it holds (``kmvipe run --rerun …``)."""

    path: Path | None = None
    """An ``.rrd`` file to write (``rerun out.rrd`` opens it)."""
    connect: str | None = None
    """A live viewer to stream to, e.g. ``rerun+http://127.0.0.1:9876/proxy`` (start ``rerun`` first)."""
    image_every: int = 5
    """Log every Nth frame's image (by seq): images are most of a recording's size. Every pose is logged."""
    map_every_s: float = 30.0
    """Refresh the map points this often while the stream runs (each refresh is a full export by the mapstore);
    0: only at end of stream."""
    map_max_points: int = 500_000
    """Most map points per refresh; a larger map is subsampled evenly."""
    queries: tuple[str, ...] = ()
    """Texts asked of the gateway at end of stream, whose answers are logged under ``world/queries``."""
    query_top_k: int = 200
    """Best points logged per query text."""

    def __post_init__(self) -> None:
        if self.path is None and self.connect is None:
            raise ConfigError("a Rerun recording needs a file (--rerun out.rrd) or a viewer (--rerun-connect URL)")
        if self.connect is not None and not self.connect.startswith(VIEWER_SCHEMES):
            raise ConfigError(f"Rerun viewer address {self.connect!r} must start with {', '.join(VIEWER_SCHEMES)} "
                              f"(e.g. {DEFAULT_VIEWER})")
        if self.image_every < 1:
            raise ConfigError(f"--rerun-every must be at least 1, not {self.image_every}")
        if self.map_every_s < 0:
            raise ConfigError(f"--rerun-map-every must be 0 (end of stream only) or more, not {self.map_every_s}")


def target_settings(target: str | None, connect: str | None = None, **more) -> RerunSettings | None:
    """Settings from ``--rerun TARGET`` (a file, or a viewer address) and ``--rerun-connect URL``; None when neither
    is given."""
    if target is None and connect is None:
        return None
    if target is not None and target.startswith(VIEWER_SCHEMES):
        if connect is not None and connect != target:
            raise ConfigError("give one viewer address: --rerun URL or --rerun-connect URL")
        return RerunSettings(connect=target, **more)
    return RerunSettings(path=Path(target) if target is not None else None, connect=connect, **more)


def load_rerun() -> ModuleType:
    """The ``rerun`` module; a ConfigError saying what to install when rerun-sdk is missing."""
    try:
        import rerun
    except ImportError as exc:
        raise ConfigError(f"recording to Rerun needs the rerun-sdk package: {RERUN_INSTALL} (or install kmvipe with "
                          "its rerun extra)") from exc
    return rerun


def sinks(settings: RerunSettings) -> list:
    """The Rerun sinks a recording streams to: the file, the live viewer, or both."""
    rr = load_rerun()
    out = [rr.FileSink(str(settings.path))] if settings.path is not None else []
    return out + ([rr.GrpcSink(settings.connect)] if settings.connect is not None else [])


# --- pure mapping ---------------------------------------------------------------------------------------------
def world() -> Entity:
    """The world's axes: those of the first camera (OpenCV's right, down, forward). Log it static."""
    return WORLD, load_rerun().ViewCoordinates.RDF


def scale_intrinsics(k: np.ndarray, from_size: tuple[int, int], to_size: tuple[int, int]) -> np.ndarray:
    """(4,) ``fx, fy, cx, cy`` of an image of ``from_size`` (W, H) for the same view at ``to_size``
    (docs/CONVENTIONS.md: ``fx' = s·fx``, ``cx' = s·(cx + 0.5) − 0.5``)."""
    s = np.array(to_size, np.float64) / np.array(from_size, np.float64)
    return camera.scale_intrinsics(k, s[0], s[1])


def pinhole(k: np.ndarray, size: tuple[int, int]) -> Entity:
    """The frustum of intrinsics ``k`` (4,) of an image of ``size`` (W, H). Rerun puts pixel centres at +0.5
    (the image spans [0, W]); KM-ViPE at integers (it spans [-0.5, W-0.5]): the principal point moves by 0.5."""
    fx, fy, cx, cy = map(float, k)
    return IMAGE, load_rerun().Pinhole(focal_length=[fx, fy], principal_point=[cx + 0.5, cy + 0.5],
                                       resolution=[int(size[0]), int(size[1])])


def camera_pose(world_from_cam: np.ndarray) -> Entity:
    """(4, 4) ``world_from_cam`` as the camera entity's transform (Rerun's parent-from-child is the same map)."""
    t = np.asarray(world_from_cam, np.float64)
    return CAMERA, load_rerun().Transform3D(translation=t[:3, 3], mat3x3=t[:3, :3])


def frame_image(frame: Frame) -> list[Entity]:
    """The frame's image as it came (JPEG bytes, or raw RGB), and its sensor depth (metres) when it has one."""
    rr = load_rerun()
    image = (rr.EncodedImage(contents=frame.jpeg, media_type="image/jpeg") if frame.jpeg is not None
             else rr.Image(frame.image, color_model="RGB"))
    out = [(IMAGE, image)]
    if frame.depth is not None:
        out.append((DEPTH, rr.DepthImage(frame.depth, meter=1.0)))
    return out


def centres(world_from_cams: np.ndarray) -> np.ndarray:
    """(N, 3) camera centres of (N, 4, 4) poses."""
    return np.asarray(world_from_cams, np.float64).reshape(-1, 4, 4)[:, :3, 3]


def trajectory(world_from_cams: np.ndarray) -> Entity:
    """The camera path through (N, 4, 4) poses in frame order."""
    return TRAJECTORY, load_rerun().LineStrips3D([centres(world_from_cams)], colors=[TRAJECTORY_COLOUR])


def keyframes(world_from_cams: np.ndarray) -> Entity:
    return KEYFRAMES, load_rerun().Points3D(centres(world_from_cams), colors=[KEYFRAME_COLOUR])


def map_points(xyz: np.ndarray, rgb: np.ndarray, max_points: int) -> Entity:
    """(N, 3) points with (N, 3) uint8 colours, evenly subsampled to at most ``max_points``."""
    step = max(1, -(-len(xyz) // max(1, max_points)))
    return MAP, load_rerun().Points3D(np.asarray(xyz)[::step], colors=np.asarray(rgb, np.uint8)[::step])


def query_path(text: str) -> str:
    return f"{QUERIES}/{load_rerun().escape_entity_path_part(text)}"


def query_answer(result: dict) -> list[Entity]:
    """One text's answer from the gateway (``TextResult`` of ``POST /v1/streams/<s>/query``): its regions as boxes
    labelled with text and score, and their best points, highlighted."""
    rr = load_rerun()
    path, regions = query_path(result["text"]), result.get("regions", [])
    lo = np.array([r["box_min"] for r in regions], np.float64).reshape(-1, 3)
    hi = np.array([r["box_max"] for r in regions], np.float64).reshape(-1, 3)
    boxes = rr.Boxes3D(centers=(lo + hi) / 2, half_sizes=(hi - lo) / 2, colors=[HIGHLIGHT],
                       labels=[f"{result['text']} {r['score']:.2f}" for r in regions])
    best = [p["xyz"] for p in result.get("top_points", [])] + [s for r in regions for s in r.get("samples", [])]
    points = rr.Points3D(np.array(best, np.float64).reshape(-1, 3), colors=[HIGHLIGHT], radii=[-3.0])
    return [(path, boxes), (f"{path}/points", points)]
