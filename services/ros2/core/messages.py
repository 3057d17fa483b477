"""KM-ViPE's poses, intrinsics and map as ROS 2 messages, and ROS 2 images as RGB arrays (pure: arrays in, message
objects or CDR bytes out).

Messages are built and (de)serialised by ``rosbags`` (Ternaris, Apache-2.0): its typestore holds the ROS 2 message
definitions, serialises CDR as rmw implementations do, and computes each type's RIHS01 hash (REP 2016) from the
definition — the hash rmw_zenoh puts in its keys (``typestore().hash_rihs01``; tests/test_ros2_names.py checks it
against the hashes ``ros2 topic info -v`` prints).

Frames: KM-ViPE's world is the first camera's optical frame (x right, y down, z forward; docs/CONVENTIONS.md) and
its poses are ``world_from_cam``. The ROS map frame is that world turned by :func:`map_from_world` (``flu``:
x forward, y left, z up as REP 103 asks, or ``optical``: unchanged); the camera frame stays optical.
"""
from __future__ import annotations

import functools

import cv2
import numpy as np

from ...common.errors import ConfigError
from ...common.rotations import rotation_to_quaternion

TF = "tf2_msgs/msg/TFMessage"
PATH = "nav_msgs/msg/Path"
CLOUD = "sensor_msgs/msg/PointCloud2"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
IMAGE_TYPES = (IMAGE, COMPRESSED)
ROSBAGS_REQUIREMENT = "rosbags>=0.11"

FLU_FROM_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
"""x forward = z optical, y left = −x optical, z up = −y optical."""
FLOAT32 = 7  # sensor_msgs/PointField.FLOAT32
POINT_STEP = 16  # x, y, z float32 and the packed rgb float32
_BAYER = {"bayer_rggb8": cv2.COLOR_BayerBG2RGB, "bayer_bggr8": cv2.COLOR_BayerRG2RGB,
          "bayer_gbrg8": cv2.COLOR_BayerGR2RGB, "bayer_grbg8": cv2.COLOR_BayerGB2RGB}  # as cv_bridge maps them
_CHANNELS = {"rgb8": 3, "bgr8": 3, "8UC3": 3, "rgba8": 4, "bgra8": 4, "8UC4": 4, "mono8": 1, "8UC1": 1,
             **{name: 1 for name in _BAYER}}
IMAGE_ENCODINGS = tuple(_CHANNELS)


@functools.cache
def typestore():
    """The ROS 2 Jazzy message definitions (those used here are identical, with equal hashes, from Humble on)."""
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError as exc:
        raise ConfigError(f"ROS 2 messages need the rosbags package: pip install '{ROSBAGS_REQUIREMENT}'") from exc
    return get_typestore(Stores.ROS2_JAZZY)


def type_hash(msgtype: str, distro: str = "jazzy") -> str:
    """The type hash rmw_zenoh of ``distro`` writes in keys: RIHS01 from Iron on, ``TypeHashNotSupported`` on Humble."""
    from .names import HASH_NOT_SUPPORTED

    return HASH_NOT_SUPPORTED if distro == "humble" else typestore().hash_rihs01(msgtype)


def serialize(msg) -> bytes:
    """A message object → CDR bytes (little endian, with the 4-byte encapsulation header)."""
    return bytes(typestore().serialize_cdr(msg, msg.__msgtype__))


def deserialize(payload: bytes | memoryview, msgtype: str):
    """CDR bytes → the message object of ``msgtype``."""
    return typestore().deserialize_cdr(payload, msgtype)


def _t(name: str):
    return typestore().types[name]


def ros_time(t_ns: int):
    """``builtin_interfaces/Time`` of ``t_ns`` (nanoseconds since the epoch; nanosec always in [0, 1e9))."""
    sec, nanosec = divmod(int(t_ns), 1_000_000_000)
    return _t("builtin_interfaces/msg/Time")(sec=sec, nanosec=nanosec)


def time_ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def header(t_ns: int, frame_id: str):
    return _t("std_msgs/msg/Header")(stamp=ros_time(t_ns), frame_id=frame_id)


def map_from_world(axes: str) -> np.ndarray:
    """(4, 4) rotation from KM-ViPE's world to the ROS map frame (``flu`` or ``optical``)."""
    out = np.eye(4)
    if axes == "flu":
        out[:3, :3] = FLU_FROM_OPTICAL
    elif axes != "optical":
        raise ValueError(f"axes {axes!r} must be flu or optical")
    return out


def _check_poses(poses: np.ndarray, stamps_ns: np.ndarray) -> np.ndarray:
    poses = np.asarray(poses, np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(stamps_ns) != len(poses):
        raise ValueError(f"poses must be (N, 4, 4) with N stamps, got {poses.shape} and {len(stamps_ns)} stamps")
    return poses


def _pose_parts(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return poses[:, :3, 3], rotation_to_quaternion(poses[:, :3, :3])  # (N, 3), (N, 4) x y z w


def tf_message(map_from_cam: np.ndarray, stamps_ns: np.ndarray, map_frame: str, camera_frame: str):
    """``tf2_msgs/TFMessage`` with one ``map_frame → camera_frame`` transform per pose.

    ``map_from_cam``: (N, 4, 4) float64, the camera's pose in the map frame; ``stamps_ns``: (N,) int64."""
    poses = _check_poses(map_from_cam, stamps_ns)
    xyz, quat = _pose_parts(poses)
    vec, rot = _t("geometry_msgs/msg/Vector3"), _t("geometry_msgs/msg/Quaternion")
    tf, stamped = _t("geometry_msgs/msg/Transform"), _t("geometry_msgs/msg/TransformStamped")
    return _t(TF)(transforms=[
        stamped(header=header(int(t), map_frame), child_frame_id=camera_frame,
                transform=tf(translation=vec(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                             rotation=rot(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))))
        for t, p, q in zip(stamps_ns, xyz, quat)])


def path_message(map_from_cam: np.ndarray, stamps_ns: np.ndarray, map_frame: str, t_ns: int):
    """``nav_msgs/Path`` of the camera positions and orientations in ``map_frame``, stamped ``t_ns``."""
    poses = _check_poses(map_from_cam, stamps_ns)
    xyz, quat = _pose_parts(poses)
    point, rot = _t("geometry_msgs/msg/Point"), _t("geometry_msgs/msg/Quaternion")
    pose, stamped = _t("geometry_msgs/msg/Pose"), _t("geometry_msgs/msg/PoseStamped")
    return _t(PATH)(header=header(t_ns, map_frame), poses=[
        stamped(header=header(int(t), map_frame),
                pose=pose(position=point(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                          orientation=rot(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))))
        for t, p, q in zip(stamps_ns, xyz, quat)])


def pack_rgb(rgb: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 → (N,) float32 whose bits are ``0x00RRGGBB``: the ``rgb`` field RViz and PCL read."""
    rgb = np.asarray(rgb, np.uint8).astype(np.uint32)
    return ((rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]).view(np.float32)


def point_cloud(xyz: np.ndarray, rgb: np.ndarray, frame: str, t_ns: int):
    """``sensor_msgs/PointCloud2`` (unorganised, little endian) with float32 fields x, y, z, rgb.

    ``xyz``: (N, 3) points in ``frame``; ``rgb``: (N, 3) uint8."""
    xyz = np.asarray(xyz, np.float32)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or np.shape(rgb) != xyz.shape:
        raise ValueError(f"xyz and rgb must both be (N, 3), got {xyz.shape} and {np.shape(rgb)}")
    rows = np.empty((len(xyz), 4), np.float32)
    rows[:, :3], rows[:, 3] = xyz, pack_rgb(rgb)
    field = _t("sensor_msgs/msg/PointField")
    fields = [field(name=n, offset=4 * i, datatype=FLOAT32, count=1) for i, n in enumerate(("x", "y", "z", "rgb"))]
    return _t(CLOUD)(header=header(t_ns, frame), height=1, width=len(xyz), fields=fields, is_bigendian=False,
                     point_step=POINT_STEP, row_step=POINT_STEP * len(xyz), data=rows.reshape(-1).view(np.uint8),
                     is_dense=bool(np.isfinite(xyz).all()))


def camera_info(intrinsics: np.ndarray, width: int, height: int, frame: str, t_ns: int):
    """``sensor_msgs/CameraInfo`` of a pinhole camera ``(fx, fy, cx, cy)`` (pixels of a ``width`` × ``height``
    image) with no distortion (KM-ViPE estimates none)."""
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    k = np.array([fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0])
    p = np.array([fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0])
    roi = _t("sensor_msgs/msg/RegionOfInterest")(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return _t(CAMERA_INFO)(header=header(t_ns, frame), height=int(height), width=int(width),
                           distortion_model="plumb_bob", d=np.zeros(5), k=k, r=np.eye(3).reshape(-1), p=p,
                           binning_x=0, binning_y=0, roi=roi)


def image_message(rgb: np.ndarray, t_ns: int, frame: str, encoding: str = "rgb8"):
    """``sensor_msgs/Image`` of an (H, W, 3) uint8 RGB array, as ``rgb8`` or ``bgr8`` (a camera driver's output)."""
    order = {"rgb8": rgb, "bgr8": rgb[..., ::-1]}
    if encoding not in order:
        raise ValueError(f"encoding {encoding!r}: rgb8 or bgr8")
    data = np.ascontiguousarray(order[encoding], np.uint8)
    h, w = data.shape[:2]
    return _t(IMAGE)(header=header(t_ns, frame), height=h, width=w, encoding=encoding, is_bigendian=0, step=3 * w,
                     data=data.reshape(-1))


def compressed_message(rgb: np.ndarray, t_ns: int, frame: str, fmt: str = "jpeg"):
    """``sensor_msgs/CompressedImage`` of an (H, W, 3) uint8 RGB array (``jpeg`` or ``png``)."""
    ok, buf = cv2.imencode("." + {"jpeg": "jpg", "png": "png"}[fmt], cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError(f"{fmt} encoding failed")
    return _t(COMPRESSED)(header=header(t_ns, frame), format=fmt, data=buf.reshape(-1))


def image_rgb(msg) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a ``sensor_msgs/Image`` (8-bit encodings: :data:`IMAGE_ENCODINGS`) or
    ``sensor_msgs/CompressedImage`` (anything OpenCV decodes: JPEG, PNG, …). ValueError for anything else."""
    if msg.__msgtype__ == COMPRESSED:
        bgr = cv2.imdecode(np.asarray(msg.data, np.uint8), cv2.IMREAD_COLOR)
        if bgr is None:
            raise ValueError(f"compressed image (format {msg.format!r}) could not be decoded")
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    if msg.__msgtype__ != IMAGE:
        raise ValueError(f"{msg.__msgtype__} is not an image type ({', '.join(IMAGE_TYPES)})")
    channels = _CHANNELS.get(msg.encoding)
    if channels is None:
        raise ValueError(f"image encoding {msg.encoding!r} not supported; supported: {', '.join(IMAGE_ENCODINGS)}")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if step < w * channels or len(msg.data) < step * h:
        raise ValueError(f"image data of {len(msg.data)} bytes, step {step}, is too short for {w}x{h} {msg.encoding}")
    pixels = np.asarray(msg.data, np.uint8)[: step * h].reshape(h, step)[:, : w * channels].reshape(h, w, channels)
    if msg.encoding in _BAYER:
        return cv2.cvtColor(pixels[..., 0], _BAYER[msg.encoding])
    if channels == 1:
        return np.repeat(pixels, 3, axis=2)
    rgb = pixels[..., :3]
    if msg.encoding in ("bgr8", "bgra8", "8UC3", "8UC4"):  # cv_bridge reads the untyped 8UC3/8UC4 as BGR(A)
        rgb = rgb[..., ::-1]
    return np.ascontiguousarray(rgb)
