"""ROS 2 images as a video source: a live topic over Zenoh (``ros2:/camera/image_raw``) and a recorded bag
(``.mcap``, ``.db3`` or a rosbag2 folder, read with rosbags). Both take ``sensor_msgs/Image`` and
``sensor_msgs/CompressedImage`` and stamp each frame with its header's stamp (a zero stamp: the time it was
received, or, in a bag, the time it was recorded). ``services.ingest.sources`` wraps them as ingest sources.
"""
from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from ..common.errors import BusError, KmVipeError, SourceError
from .config import Ros2Settings, RosZenohSettings
from .core import messages
from .core.names import check_topic

log = logging.getLogger(__name__)
POLL_S = 0.05


@dataclass(frozen=True)
class RosImage:
    index: int  # position in the topic or bag (0-based)
    t_ns: int  # header stamp, ns since the epoch
    rgb: np.ndarray  # (H, W, 3) uint8


@dataclass(frozen=True)
class RosImageError:
    index: int
    reason: str


def _image(index: int, msgtype: str, payload: bytes, fallback_ns: int) -> RosImage | RosImageError:
    try:
        msg = messages.deserialize(payload, msgtype)
        rgb = messages.image_rgb(msg)
    except KmVipeError:
        raise
    except Exception as exc:  # a malformed message is one bad frame, never the end of the stream
        return RosImageError(index, f"{msgtype}: {exc}")
    return RosImage(index, messages.time_ns(msg.header.stamp) or fallback_ns, rgb)


def image_type_of(topic: str, setting: str) -> str:
    """The message type assumed on ``topic`` where its key does not name it (the bridge form)."""
    if setting != "auto":
        return f"sensor_msgs/msg/{setting}"
    return messages.COMPRESSED if topic.endswith("/compressed") else messages.IMAGE


class TopicImages:
    """The images published on a ROS 2 topic, as they arrive; the oldest go when more than ``cfg.queue`` wait."""

    def __init__(self, topic: str, cfg: Ros2Settings, zenoh_settings: RosZenohSettings):
        from .transport import RosNode  # zenoh only for a live topic

        try:
            self.topic = check_topic(topic)
        except ValueError as exc:
            raise SourceError(f"ros2: source: {exc}") from exc
        self.cfg, self.dropped = cfg, 0
        self._hint = image_type_of(topic, cfg.image_type)
        self._items: deque[tuple[str, bytes, int]] = deque()
        self._ready = threading.Condition()
        self._router = zenoh_settings.connect
        try:
            self._node = RosNode(cfg, zenoh_settings)
        except BusError as exc:
            raise SourceError(f"cannot join the ROS 2 Zenoh network at {self._router} for {topic} "
                              f"(KMVIPE_ROS2_ZENOH_CONNECT, KMVIPE_ROS2_ZENOH_MODE): {exc}") from exc
        types = messages.IMAGE_TYPES if cfg.form == "rmw_zenoh" else (self._hint,)
        self.selector = self._node.subscribe(topic, types, self._on_sample)

    def _on_sample(self, key: str, msgtype: str | None, payload: bytes) -> None:
        with self._ready:
            if len(self._items) >= self.cfg.queue:
                self._items.popleft()
                self.dropped += 1
            self._items.append((msgtype or self._hint, payload, time.time_ns()))
            self._ready.notify()

    def _next(self, timeout: float) -> tuple[str, bytes, int] | None:
        with self._ready:
            if not self._items and not self._ready.wait_for(lambda: bool(self._items), timeout):
                return None
            return self._items.popleft()

    def images(self) -> Iterator[RosImage | RosImageError]:
        """Until no image came for ``idle_timeout_s`` (SourceError if none came in ``first_message_timeout_s``)."""
        index, last = 0, time.monotonic()
        try:
            while True:
                item = self._next(POLL_S)
                if item is None:
                    idle = time.monotonic() - last
                    if index == 0 and idle > self.cfg.first_message_timeout_s:
                        raise SourceError(self._nothing_heard())
                    if index and self.cfg.idle_timeout_s and idle > self.cfg.idle_timeout_s:
                        log.info("ROS 2 topic went quiet: end of stream", extra={"topic": self.topic, "images": index,
                                                                               "dropped": self.dropped})
                        return
                    continue
                msgtype, payload, received_ns = item
                last = time.monotonic()
                if msgtype not in messages.IMAGE_TYPES:
                    yield RosImageError(index, f"{msgtype} on {self.topic} is not an image type")
                else:
                    yield _image(index, msgtype, payload, received_ns)
                index += 1
        finally:
            self._node.close()

    def _nothing_heard(self) -> str:
        return (f"no image on ROS 2 topic {self.topic} (Zenoh key {self.selector}) within "
                f"{self.cfg.first_message_timeout_s:.0f} s: check that a node publishes it (`ros2 topic info "
                f"{self.topic}`), that the ROS router is at {self._router} (KMVIPE_ROS2_ZENOH_CONNECT), the domain "
                f"({self.cfg.domain_id}, KMVIPE_ROS2_DOMAIN_ID) and the form ({self.cfg.form}, KMVIPE_ROS2_FORM: "
                "rmw_zenoh for nodes on rmw_zenoh_cpp, bridge behind zenoh-bridge-ros2dds)")


def _reader(path: Path):
    try:
        from rosbags.rosbag2 import Reader
    except ImportError as exc:
        raise SourceError(f"reading a ROS 2 bag needs the rosbags package: pip install "
                          f"'{messages.ROSBAGS_REQUIREMENT}'") from exc
    return Reader(path)


class BagImages:
    """The images of one topic of a rosbag2 recording (a folder with ``metadata.yaml``, or one ``.mcap`` /
    ``.db3`` file), in recording order. ``topic`` may be empty when the bag has exactly one image topic."""

    def __init__(self, path: Path, topic: str = ""):
        self.path = path
        try:
            with _reader(path) as reader:
                images = {c.topic: c.msgtype for c in reader.connections if c.msgtype in messages.IMAGE_TYPES}
                self.topic = self._choose(topic, images, sorted({c.topic for c in reader.connections}))
                self.msgtype = images[self.topic]
                self.count = sum(c.msgcount for c in reader.connections if c.topic == self.topic)
                span_s = (reader.end_time - reader.start_time) / 1e9
        except SourceError:
            raise
        except Exception as exc:  # rosbags' ReaderError, a missing metadata.yaml, a truncated file
            raise SourceError(f"cannot read ROS 2 bag {path}: {exc}") from exc
        # the rate realtime pacing replays at: the topic's images over the whole recording (reading every stamp
        # of a large bag first would cost as much as the run)
        self.fps = (self.count - 1) / span_s if self.count > 1 and span_s > 0 else None

    def _choose(self, topic: str, images: dict[str, str], every: list[str]) -> str:
        listed = ", ".join(f"{t} ({images[t].rsplit('/', 1)[-1]})" for t in sorted(images)) or "none"
        if topic:
            if topic not in images:
                raise SourceError(f"ROS 2 bag {self.path} has no image topic {topic}; its image topics: {listed}")
            return topic
        if len(images) == 1:
            return next(iter(images))
        if not images:
            raise SourceError(f"ROS 2 bag {self.path} has no sensor_msgs/Image or CompressedImage topic "
                              f"(topics: {', '.join(every) or 'none'})")
        raise SourceError(f"ROS 2 bag {self.path} has several image topics ({listed}): choose one with --topic "
                          "(KMVIPE_INGEST_TOPIC)")

    def images(self) -> Iterator[RosImage | RosImageError]:
        with _reader(self.path) as reader:
            chosen = [c for c in reader.connections if c.topic == self.topic]
            for index, (conn, logged_ns, raw) in enumerate(reader.messages(connections=chosen)):
                yield _image(index, conn.msgtype, raw, logged_ns)
