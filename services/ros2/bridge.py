"""The ROS 2 bridge: a stream's poses, intrinsics and map from the KM-ViPE bus, published as ROS 2 messages.

In: ``kmvipe/<s>/pose`` (``Poses``), ``kmvipe/<s>/intrinsics`` (``Intrinsics``), the mapstore's
``kmvipe/<s>/map/export`` queryable (``MapChunk``). Out (ROS 2, CDR): ``tf2_msgs/TFMessage`` map → camera for every
frame as its first pose arrives, ``nav_msgs/Path`` of every frame's latest pose (at most every ``path_period_s``),
``sensor_msgs/PointCloud2`` of the map (every ``map_period_s``), ``sensor_msgs/CameraInfo`` when the intrinsics are
refined and with every map refresh.
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

import numpy as np

from ..common import keys
from ..common.bus import Bus
from ..common.errors import DecodeError, KmVipeError
from ..common.schema import Intrinsics, MapChunk, Poses, decode
from .config import Ros2Settings
from .core import messages
from .core.trajectory import Trajectory, subsample
from .transport import RosNode

log = logging.getLogger(__name__)
POLL_S = 0.05


@dataclass
class BridgeCounters:
    transforms: int = 0
    paths: int = 0
    clouds: int = 0
    camera_infos: int = 0
    map_failures: int = 0


class Bridge:
    """State and handlers of one stream's bridge; ``handle_*`` are called from the loop in :func:`run` only."""

    def __init__(self, cfg: Ros2Settings, node: RosNode):
        self.cfg = cfg
        self.trajectory = Trajectory()
        self.map_from_world = messages.map_from_world(cfg.axes)
        self.counters = BridgeCounters()
        self.intrinsics: Intrinsics | None = None
        self.last_stamp_ns = 0  # the newest frame stamp: the stamp of the path, the cloud and the camera info
        self.tf = node.publisher(cfg.tf_topic, messages.TF)
        self.path = node.publisher(cfg.path_topic, messages.PATH)
        self.cloud = node.publisher(cfg.cloud_topic, messages.CLOUD)
        self.camera_info = node.publisher(cfg.camera_info_topic, messages.CAMERA_INFO)

    def handle_poses(self, msg: Poses) -> None:
        new = self.trajectory.update(msg.frame_seqs, msg.stamps_ns, msg.poses, msg.tracked, msg.session)
        if not len(new.seqs):
            return
        self.last_stamp_ns = max(self.last_stamp_ns, int(new.stamps_ns.max()))
        tf = messages.tf_message(self.map_from_world @ new.world_from_cam, new.stamps_ns, self.cfg.map_frame,
                                 self.cfg.camera_frame)
        self.tf.put(messages.serialize(tf))
        self.counters.transforms += len(new.seqs)

    def handle_intrinsics(self, msg: Intrinsics) -> None:
        self.intrinsics = msg
        self.send_camera_info()

    def send_camera_info(self) -> None:
        k = self.intrinsics
        if k is None:
            return
        info = messages.camera_info(k.intrinsics, k.width, k.height, self.cfg.camera_frame,
                                    self.last_stamp_ns or k.t_ns)
        self.camera_info.put(messages.serialize(info))
        self.counters.camera_infos += 1

    def send_path(self) -> None:
        stamps, poses = self.trajectory.take_path()
        keep = subsample(len(stamps), self.cfg.path_max_poses)
        path = messages.path_message(self.map_from_world @ poses[keep], stamps[keep], self.cfg.map_frame,
                                     self.last_stamp_ns)
        self.path.put(messages.serialize(path))
        self.counters.paths += 1

    def send_map(self, xyz: np.ndarray, rgb: np.ndarray) -> None:
        """Publish the (N, 3) world points ``xyz`` with their (N, 3) uint8 colours (subsampled to the limit)."""
        keep = subsample(len(xyz), self.cfg.map_max_points)
        points = xyz[keep].astype(np.float64) @ self.map_from_world[:3, :3].T
        cloud = messages.point_cloud(points.astype(np.float32), rgb[keep], self.cfg.map_frame, self.last_stamp_ns)
        self.cloud.put(messages.serialize(cloud))
        self.counters.clouds += 1


def fetch_map(bus: Bus, cfg: Ros2Settings) -> tuple[np.ndarray, np.ndarray]:
    """The stream's fused map from the mapstore, chunk by chunk: ``(xyz (N, 3) float32, rgb (N, 3) uint8)``.
    Raises KmVipeError (no mapstore, a timeout, a bad reply)."""
    xyz, rgb, index, n_chunks = [], [], 0, 1
    while index < n_chunks:
        selector = keys.map_key(cfg.stream, "export") + f"?chunk={index};chunk_size={cfg.map_chunk_points}"
        try:
            chunk = decode(bus.request(selector, timeout=cfg.map_timeout_s, service="mapstore"), MapChunk)
        except (RuntimeError, DecodeError) as exc:
            raise KmVipeError(f"map export of stream '{cfg.stream}' failed: {exc}") from exc
        xyz.append(chunk.xyz)
        rgb.append(chunk.rgb)
        index, n_chunks = index + 1, chunk.n_chunks
    return np.concatenate(xyz).reshape(-1, 3), np.concatenate(rgb).reshape(-1, 3)


def run(cfg: Ros2Settings, bus: Bus, node: RosNode, stop: threading.Event) -> BridgeCounters:
    """Bridge stream ``cfg.stream`` until ``stop`` is set."""
    bridge = Bridge(cfg, node)
    inbox = bus.inbox({keys.topic(cfg.stream, keys.POSE): [Poses],
                       keys.topic(cfg.stream, keys.INTRINSICS): [Intrinsics]}, lossless=True)
    bus.ready()
    log.info("bridging to ROS 2", extra={"stream": cfg.stream, "form": cfg.form, "domain_id": cfg.domain_id})
    next_path = next_map = time.monotonic()
    while not stop.is_set():
        delivery = inbox.get(POLL_S)
        if delivery is not None:
            if isinstance(delivery.msg, Poses):
                bridge.handle_poses(delivery.msg)
            else:
                bridge.handle_intrinsics(delivery.msg)
        now = time.monotonic()
        if bridge.trajectory.changed and now >= next_path:
            bridge.send_path()
            next_path = now + cfg.path_period_s
        if cfg.map_period_s and now >= next_map and inbox.qsize() == 0:
            next_map = now + cfg.map_period_s
            _refresh_map(bridge, bus, cfg)
    return bridge.counters


def _refresh_map(bridge: Bridge, bus: Bus, cfg: Ros2Settings) -> None:
    try:
        xyz, rgb = fetch_map(bus, cfg)
    except KmVipeError as exc:  # no map yet, or the mapstore restarting: try again next period
        bridge.counters.map_failures += 1
        if bridge.counters.map_failures == 1:
            log.warning("no map to publish yet", extra={"stream": cfg.stream, "error": str(exc)})
        return
    if len(xyz):
        bridge.send_map(xyz, rgb)
    bridge.send_camera_info()
