"""Settings of the ROS 2 side (env prefixes ``KMVIPE_ROS2_`` and ``KMVIPE_ROS2_ZENOH_``, or the ``[ros2]`` and
``[ros2_zenoh]`` tables of the ``KMVIPE_CONFIG`` file).

Two Zenoh sessions meet here: KM-ViPE's own bus (``KMVIPE_BUS_*``, :class:`services.common.config.BusSettings`) and
the ROS 2 graph's Zenoh network (:class:`RosZenohSettings`), by default the router that ``rmw_zenohd`` or
``zenoh-bridge-ros2dds`` runs on ``tcp/127.0.0.1:7447``. They may be one network; keeping two sessions lets each
have its own endpoints and credentials.
"""
from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator
from pydantic_settings import SettingsConfigDict

from ..common.config import BusSettings
from ..common.config_file import KmVipeSettings
from ..common.keys import DEFAULT_STREAM, check_name
from .core.names import check_frame, check_node_name, check_topic

ROS_ROUTER = "tcp/127.0.0.1:7447"
"""Where both ``rmw_zenohd`` (rmw_zenoh's router) and ``zenoh-bridge-ros2dds`` (router mode since 0.11) listen."""


class RosZenohSettings(BusSettings):
    """The Zenoh session on the ROS 2 side: every field of :class:`BusSettings`, under ``KMVIPE_ROS2_ZENOH_``."""

    model_config = SettingsConfigDict(env_prefix="KMVIPE_ROS2_ZENOH_", env_file=".env", extra="ignore")

    mode: Literal["peer", "client", "router"] = "client"
    """client: every sample goes through the ROS router, so no ROS node has to reach this process directly."""
    connect: list[str] = [ROS_ROUTER]


class Ros2Settings(KmVipeSettings):
    """What the bridge publishes, where, and how ROS image input is read (``KMVIPE_ROS2_*``)."""

    model_config = SettingsConfigDict(env_prefix="KMVIPE_ROS2_", env_file=".env", extra="ignore")

    stream: str = DEFAULT_STREAM
    """The KM-ViPE stream whose poses, intrinsics and map the bridge publishes."""
    form: Literal["rmw_zenoh", "bridge"] = "rmw_zenoh"
    """Key expressions: ``rmw_zenoh`` speaks to ROS 2 nodes running ``RMW_IMPLEMENTATION=rmw_zenoh_cpp`` directly
    (``<domain>/<topic>/<dds type>/<type hash>``, an attachment on every sample, liveliness tokens for the graph);
    ``bridge`` speaks to ``zenoh-bridge-ros2dds`` (the topic name without its leading ``/``; the bridge turns it
    into DDS for nodes on any RMW)."""
    domain_id: int = Field(0, ge=0, le=232)
    """``ROS_DOMAIN_ID`` of the ROS graph (rmw_zenoh form only: it is the first chunk of every key)."""
    distro: Literal["jazzy", "kilted", "rolling", "humble"] = "jazzy"
    """The ROS 2 release of the rmw_zenoh nodes: Humble's rmw_zenoh puts ``TypeHashNotSupported`` where later
    releases put the type's RIHS01 hash."""
    node_name: str = "kmvipe"
    """The node the rmw_zenoh form announces its publishers and subscriptions under (``ros2 node list``)."""
    map_frame: str = "map"
    camera_frame: str = "camera_optical_frame"
    """The child frame of every transform: the camera's optical frame (x right, y down, z forward)."""
    axes: Literal["flu", "optical"] = "flu"
    """Axes of ``map_frame``: ``flu`` turns KM-ViPE's world (the first camera's optical axes: x right, y down,
    z forward) into ROS's x forward, y left, z up (REP 103), so RViz shows the floor below; ``optical`` keeps it."""
    tf_topic: str = "/tf"
    path_topic: str = "/kmvipe/path"
    cloud_topic: str = "/kmvipe/map"
    camera_info_topic: str = "/kmvipe/camera_info"
    depth: int = Field(10, ge=1, le=10_000)
    """QoS history depth the rmw_zenoh form announces for its publishers (KEEP_LAST, RELIABLE, VOLATILE)."""
    path_period_s: float = Field(0.5, gt=0)
    """The path is sent at most this often (it grows with every frame; transforms go out at once)."""
    path_max_poses: int = Field(5_000, ge=2)
    """A longer trajectory is sent evenly subsampled to this many poses (first and last kept): the whole path
    goes out each time, and a 30 Hz hour of it would be 10 MB a message."""
    map_period_s: float = Field(5.0, ge=0)
    """The point cloud is fetched from the mapstore (``map/export``) and sent this often; 0 sends none."""
    map_max_points: int = Field(200_000, ge=1)
    """A bigger map is sent subsampled evenly to this many points."""
    map_chunk_points: int = Field(100_000, ge=1, le=1_000_000)
    map_timeout_s: float = Field(5.0, gt=0)
    image_type: Literal["auto", "Image", "CompressedImage"] = "auto"
    """The type on a ``ros2:`` image topic; auto: from the key (rmw_zenoh form) or, in the bridge form, from the
    name (``.../compressed`` → CompressedImage, else Image)."""
    queue: int = Field(4, ge=1)
    """Images of a ``ros2:`` topic held for the pipeline; when it is behind, the oldest go first (a live camera)."""
    first_message_timeout_s: float = Field(60.0, gt=0)
    """A ``ros2:`` source with no image after this long stops with an error saying what to check."""
    idle_timeout_s: float = Field(10.0, ge=0)
    """A ``ros2:`` source ends its stream when no image came for this long (a bag that finished playing);
    0 waits for ever."""

    @field_validator("stream")
    @classmethod
    def _stream(cls, value: str) -> str:
        return check_name(value)

    @field_validator("tf_topic", "path_topic", "cloud_topic", "camera_info_topic")
    @classmethod
    def _topic(cls, value: str) -> str:
        return check_topic(value)

    @field_validator("map_frame", "camera_frame")
    @classmethod
    def _frame(cls, value: str) -> str:
        return check_frame(value)

    @field_validator("node_name")
    @classmethod
    def _node(cls, value: str) -> str:
        return check_node_name(value)
