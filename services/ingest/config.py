"""Settings of the ingest service (env prefix ``KMVIPE_INGEST_``, or ``[ingest]`` of the ``KMVIPE_CONFIG`` file)."""
from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator
from pydantic_settings import SettingsConfigDict

from ..common.config_file import KmVipeSettings
from ..common.keys import DEFAULT_STREAM


class IngestSettings(KmVipeSettings):
    model_config = SettingsConfigDict(env_prefix="KMVIPE_INGEST_", env_file=".env", extra="ignore")

    source: str = ""
    """Video file, image folder (plain, TUM ``rgb.txt``, KITTI ``image_0/``), camera index or ``/dev/videoN``,
    ``rtsp://`` / ``http(s)://`` URL, a ROS 2 bag (``.mcap``, ``.db3`` or a rosbag2 folder), a live ROS 2 image topic
    over Zenoh (``ros2:/camera/image_raw``; settings ``KMVIPE_ROS2_*``, services/ros2/README.md), or
    ``synth:frames=200,seed=0`` for the synthetic world."""
    topic: str = ""
    """The image topic (``sensor_msgs/Image`` or ``CompressedImage``) of a ROS 2 bag source; empty: the bag's only
    image topic (``kmvipe run bag.mcap --topic /camera/image_raw``)."""
    stream: str = DEFAULT_STREAM
    """Stream name: the ``<s>`` in every key, so one deployment can serve several cameras."""
    pacing: Literal["lossless", "realtime"] = "lossless"
    """lossless: wait for credit, every frame is delivered; realtime: keep the source's pace, drop when behind."""
    encoding: Literal["jpeg", "raw"] = "jpeg"
    jpeg_quality: int = Field(90, ge=10, le=100)
    intrinsics: list[float] | None = None
    """Optional hint ``[fx, fy, cx, cy]`` in source pixels; without it, features guesses and BA refines."""
    use_depth: bool = False
    """Send sensor depth when the source has it (a folder's ``depth.txt``; ``synth:depth=1``). Opt-in: a depth
    file that happens to lie in a folder is not used without it (``kmvipe run --depth``)."""
    depth_scale: float | None = Field(None, gt=0)
    """Depth PNG units per metre; default per dataset: 1000 (millimetres) for an Aria Digital Twin folder, else
    5000 (TUM RGB-D)."""
    max_frames: int | None = Field(None, ge=1)
    stride: int = Field(1, ge=1)
    fps: float | None = Field(None, gt=0)
    """Rate of a file source in realtime mode (default: the file's own rate, else 10)."""
    credit_ttl_s: float = Field(5.0, gt=0)
    """A consumer that has granted no credit for this long no longer holds the stream back."""
    hold_after_end_s: float = Field(60.0, ge=0)
    """Lossless: after its end of stream the source stays announced until features has ended the stream too (at
    most this long), so a features that restarts meanwhile still finds the stream and gets what it lost."""
    wait_for_consumer_s: float = Field(60.0, ge=0)
    """How long to wait for the first consumer's credit before reading the source (so the first frames of a
    file are not dropped while the pipeline connects); lossless mode then gives up with a clear error."""

    @field_validator("intrinsics")
    @classmethod
    def _four(cls, value: list[float] | None) -> list[float] | None:
        if value is not None and (len(value) != 4 or min(value[:2]) <= 0):
            raise ValueError("intrinsics must be [fx, fy, cx, cy] with fx, fy > 0")
        return value
