"""KM-ViPE arrays ↔ ROS 2 messages: each message is serialised to CDR, read back with rosbags' deserialiser and
compared with the arrays it was made from."""
from __future__ import annotations

import numpy as np
import pytest

from services.common.rotations import quaternion_to_rotation
from services.ros2.core import messages as m

RNG = np.random.default_rng(7)


def random_poses(n: int) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = quaternion_to_rotation(RNG.standard_normal((n, 4)))
    poses[:, :3, 3] = RNG.uniform(-5, 5, (n, 3))
    return poses


def roundtrip(msg):
    return m.deserialize(m.serialize(msg), msg.__msgtype__)


def pose_of(translation, rotation) -> np.ndarray:
    out = np.eye(4)
    out[:3, 3] = [translation.x, translation.y, translation.z]
    out[:3, :3] = quaternion_to_rotation(np.array([[rotation.x, rotation.y, rotation.z, rotation.w]]))[0]
    return out


def test_tf_message_carries_every_pose_with_its_stamp_and_frames():
    poses, stamps = random_poses(5), np.array([0, 1, 999_999_999, 1_000_000_000, 1_700_000_000_123_456_789])
    got = roundtrip(m.tf_message(poses, stamps, "map", "camera_optical_frame"))
    assert len(got.transforms) == 5
    for tf, pose, stamp in zip(got.transforms, poses, stamps):
        assert (tf.header.frame_id, tf.child_frame_id) == ("map", "camera_optical_frame")
        assert m.time_ns(tf.header.stamp) == stamp and 0 <= tf.header.stamp.nanosec < 1_000_000_000
        np.testing.assert_allclose(pose_of(tf.transform.translation, tf.transform.rotation), pose, atol=1e-12)


def test_path_message_holds_the_poses_in_order():
    poses, stamps = random_poses(4), np.arange(4) * 100_000_000 + 5
    got = roundtrip(m.path_message(poses, stamps, "map", 77))
    assert got.header.frame_id == "map" and m.time_ns(got.header.stamp) == 77
    assert [m.time_ns(p.header.stamp) for p in got.poses] == stamps.tolist()
    for ps, pose in zip(got.poses, poses):
        np.testing.assert_allclose(pose_of(ps.pose.position, ps.pose.orientation), pose, atol=1e-12)


def test_flu_map_axes_put_the_first_cameras_view_forward_and_its_down_below():
    rot = m.map_from_world("flu")[:3, :3]
    np.testing.assert_allclose(rot @ [0, 0, 1], [1, 0, 0])  # optical forward → x forward
    np.testing.assert_allclose(rot @ [1, 0, 0], [0, -1, 0])  # optical right → −y (y is left)
    np.testing.assert_allclose(rot @ [0, 1, 0], [0, 0, -1])  # optical down → −z (z is up)
    assert np.isclose(np.linalg.det(rot), 1.0)
    np.testing.assert_array_equal(m.map_from_world("optical"), np.eye(4))


def test_point_cloud_fields_hold_the_points_and_colours():
    xyz = RNG.uniform(-3, 3, (50, 3)).astype(np.float32)
    rgb = RNG.integers(0, 256, (50, 3)).astype(np.uint8)
    got = roundtrip(m.point_cloud(xyz, rgb, "map", 12))
    assert (got.height, got.width, got.point_step, got.row_step) == (1, 50, 16, 800)
    assert [(f.name, f.offset, f.datatype, f.count) for f in got.fields] == [
        ("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("rgb", 12, 7, 1)]
    rows = np.frombuffer(np.asarray(got.data).tobytes(), np.float32).reshape(50, 4)
    np.testing.assert_array_equal(rows[:, :3], xyz)
    packed = rows[:, 3].view(np.uint32)
    np.testing.assert_array_equal(np.stack([packed >> 16, (packed >> 8) & 255, packed & 255], axis=1), rgb)
    assert got.is_dense and got.header.frame_id == "map"


def test_camera_info_is_the_pinhole_of_the_intrinsics():
    got = roundtrip(m.camera_info(np.array([500.0, 510.0, 320.5, 240.25]), 640, 480, "cam", 3))
    np.testing.assert_array_equal(got.k.reshape(3, 3), [[500, 0, 320.5], [0, 510, 240.25], [0, 0, 1]])
    np.testing.assert_array_equal(got.p.reshape(3, 4)[:, :3], got.k.reshape(3, 3))
    assert (got.width, got.height, got.header.frame_id, got.distortion_model) == (640, 480, "cam", "plumb_bob")
    np.testing.assert_array_equal(got.d, np.zeros(5))


def raw_image(pixels: np.ndarray, encoding: str, pad: int = 0):
    """An Image whose rows are ``pad`` bytes longer than the pixels (drivers align rows)."""
    h, w = pixels.shape[:2]
    rows = pixels.reshape(h, -1)
    data = np.zeros((h, rows.shape[1] + pad), np.uint8)
    data[:, : rows.shape[1]] = rows
    msg = m.image_message(np.zeros((h, w, 3), np.uint8), 5, "cam")
    return type(msg)(header=msg.header, height=h, width=w, encoding=encoding, is_bigendian=0,
                     step=data.shape[1], data=data.reshape(-1))


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "rgba8", "bgra8", "mono8", "8UC3"])
def test_raw_images_decode_to_rgb(encoding):
    rgb = RNG.integers(0, 256, (6, 5, 3)).astype(np.uint8)
    pixels = {"rgb8": rgb, "bgr8": rgb[..., ::-1], "8UC3": rgb[..., ::-1],
              "rgba8": np.dstack([rgb, np.full((6, 5), 9, np.uint8)]),
              "bgra8": np.dstack([rgb[..., ::-1], np.full((6, 5), 9, np.uint8)]), "mono8": rgb[..., 0]}[encoding]
    got = m.image_rgb(roundtrip(raw_image(np.ascontiguousarray(pixels), encoding, pad=3)))
    want = np.repeat(rgb[..., :1], 3, axis=2) if encoding == "mono8" else rgb
    np.testing.assert_array_equal(got, want)


def test_bayer_images_are_demosaiced_to_their_colour():
    colour = np.array([200, 100, 40], np.uint8)
    mosaic = np.empty((8, 8), np.uint8)  # RGGB: R at (even, even), B at (odd, odd), G elsewhere
    mosaic[0::2, 0::2], mosaic[1::2, 1::2] = colour[0], colour[2]
    mosaic[0::2, 1::2] = mosaic[1::2, 0::2] = colour[1]
    got = m.image_rgb(roundtrip(raw_image(mosaic[..., None], "bayer_rggb8")))
    np.testing.assert_array_equal(got[2:-2, 2:-2], np.broadcast_to(colour, (4, 4, 3)))


def test_compressed_images_decode_to_rgb():
    rgb = RNG.integers(0, 256, (16, 24, 3)).astype(np.uint8)
    np.testing.assert_array_equal(m.image_rgb(roundtrip(m.compressed_message(rgb, 1, "cam", "png"))), rgb)
    smooth = np.dstack([*np.meshgrid(np.arange(24) * 10, np.arange(16) * 15), np.full((16, 24), 90)]).astype(np.uint8)
    jpeg = m.image_rgb(roundtrip(m.compressed_message(smooth, 1, "cam", "jpeg")))
    assert np.abs(jpeg.astype(int) - smooth).mean() < 4


def test_undecodable_images_say_why():
    with pytest.raises(ValueError, match="not supported"):
        m.image_rgb(raw_image(np.zeros((2, 2, 2), np.uint8), "mono16"))
    short = raw_image(np.zeros((4, 4, 3), np.uint8), "rgb8")
    with pytest.raises(ValueError, match="too short"):
        m.image_rgb(type(short)(header=short.header, height=4, width=4, encoding="rgb8", is_bigendian=0, step=12,
                                data=short.data[:20]))
    bad = m.compressed_message(np.zeros((4, 4, 3), np.uint8), 1, "cam")
    with pytest.raises(ValueError, match="could not be decoded"):
        m.image_rgb(type(bad)(header=bad.header, format="jpeg", data=np.zeros(10, np.uint8)))
