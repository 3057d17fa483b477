"""The ROS 2 bridge end to end on loopback Zenoh: poses and intrinsics published on the KM-ViPE bus and a map
served by the reference map queryable come out on a separate "ROS" Zenoh network as CDR that rosbags decodes to
the same frames, stamps, poses, points and intrinsics; in the rmw_zenoh form with rmw_zenoh's attachment and
liveliness tokens, in the zenoh-bridge-ros2dds form on the bare topic keys."""
from __future__ import annotations

import threading
import time
from collections import defaultdict

import numpy as np
import pytest
import zenoh

from services.common import keys
from services.common.schema import Intrinsics, Poses
from services.ros2.bridge import run
from services.ros2.config import Ros2Settings, RosZenohSettings
from services.ros2.core import messages
from services.ros2.core.names import unpack_attachment
from services.ros2.transport import RosNode
from tests.query_api_fixtures import STREAM, bus_pair, free_port, make_scene, scene_map, wait_for
from tests.test_ros2_messages import pose_of, random_poses

K = np.array([400.0, 410.0, 160.0, 120.0])


def ros_router() -> tuple[zenoh.Session, str]:
    """A Zenoh router on loopback standing in for rmw_zenohd / zenoh-bridge-ros2dds (its session is the ROS node
    that listens)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", f'["{endpoint}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf), endpoint


def await_subscriber(session: zenoh.Session, key: str) -> None:
    """Wait until ``session`` knows of a subscriber to ``key``, so every sample it publishes next arrives."""
    publisher = session.declare_publisher(key)
    try:
        wait_for(lambda: publisher.matching_status.matching, what=f"a subscriber on {key}")
    finally:
        publisher.undeclare()


class Recorder:
    """Every sample under a selector, by key: (payload, attachment bytes or None)."""

    def __init__(self, session: zenoh.Session, selector: str):
        self.samples: dict[str, list[tuple[bytes, bytes | None]]] = defaultdict(list)
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(selector, self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        with self._lock:
            att = sample.attachment.to_bytes() if sample.attachment is not None else None
            self.samples[str(sample.key_expr)].append((sample.payload.to_bytes(), att))

    def messages(self, key: str, msgtype: str) -> list:
        with self._lock:
            return [messages.deserialize(p, msgtype) for p, _ in self.samples.get(key, [])]

    def attachments(self, key: str) -> list[bytes | None]:
        with self._lock:
            return [a for _, a in self.samples.get(key, [])]


@pytest.mark.parametrize("form", ["rmw_zenoh", "bridge"])
def test_bridge_publishes_tf_path_cloud_and_camera_info(form):
    router, endpoint = ros_router()
    recorder = Recorder(router, "**")
    km, bridge_bus = bus_pair("ba", "ros2")
    scene = make_scene(points_per_label=50)
    scene_map(scene).serve(km, STREAM)
    cfg = Ros2Settings(_env_file=None, stream=STREAM, form=form, domain_id=4, path_period_s=0.1, map_period_s=0.2)
    node = RosNode(cfg, RosZenohSettings(_env_file=None, mode="client", connect=[endpoint]))
    stop = threading.Event()
    worker = threading.Thread(target=run, args=(cfg, bridge_bus, node, stop), daemon=True)
    worker.start()
    try:
        for topic in (keys.POSE, keys.INTRINSICS):
            await_subscriber(km.session, keys.topic(STREAM, topic))
        tracked, mapped = random_poses(3), random_poses(3)
        stamps = np.array([1_700_000_000_000_000_000 + 33_333_333 * i for i in range(3)], np.int64)
        for i in range(3):  # tracking: one pose per frame as it comes
            km.publish(keys.topic(STREAM, keys.POSE), Poses(STREAM, i, int(stamps[i]), frame_seqs=np.array([i]),
                                                            stamps_ns=stamps[i:i + 1], poses=tracked[i:i + 1],
                                                            tracked=True))
        km.publish(keys.topic(STREAM, keys.POSE), Poses(STREAM, 2, int(stamps[2]), frame_seqs=np.arange(3),
                                                        stamps_ns=stamps, poses=mapped))  # mapping revises them
        km.publish(keys.topic(STREAM, keys.INTRINSICS), Intrinsics(STREAM, 2, 0, intrinsics=K, width=320, height=240))
        table = dict((topic, key) for topic, _, key in _keys(cfg))
        flu = messages.map_from_world("flu")

        def last_path():
            paths = recorder.messages(table["/kmvipe/path"], messages.PATH)
            if paths and len(paths[-1].poses) == 3:
                got = [pose_of(p.pose.position, p.pose.orientation) for p in paths[-1].poses]
                return paths[-1] if np.allclose(got, flu @ mapped, atol=1e-9) else None
            return None

        path = wait_for(last_path, what="the path of the revised poses")
        clouds = wait_for(lambda: recorder.messages(table["/kmvipe/map"], messages.CLOUD), what="a point cloud")
        infos = wait_for(lambda: recorder.messages(table["/kmvipe/camera_info"], messages.CAMERA_INFO),
                         what="camera info")

        def all_transforms():
            found = [t for msg in recorder.messages(table["/tf"], messages.TF) for t in msg.transforms]
            return found if len(found) >= 3 else None

        transforms = wait_for(all_transforms, what="a transform per frame")
    finally:
        stop.set()
        worker.join(5)
    try:
        # one transform per frame, from its first (tracked) pose; the revision sent none
        assert [messages.time_ns(t.header.stamp) for t in transforms] == stamps.tolist()
        assert {(t.header.frame_id, t.child_frame_id) for t in transforms} == {("map", "camera_optical_frame")}
        np.testing.assert_allclose([pose_of(t.transform.translation, t.transform.rotation) for t in transforms],
                                   flu @ tracked, atol=1e-9)
        assert [messages.time_ns(p.header.stamp) for p in path.poses] == stamps.tolist()
        assert path.header.frame_id == "map"

        cloud = clouds[-1]
        rows = np.frombuffer(np.asarray(cloud.data).tobytes(), np.float32).reshape(-1, 4)
        want = scene.xyz.astype(np.float64) @ flu[:3, :3].T
        order_got, order_want = np.lexsort(rows[:, :3].T), np.lexsort(want.T)
        np.testing.assert_allclose(rows[order_got, :3], want[order_want], atol=1e-5)
        packed = rows[order_got, 3].view(np.uint32)
        np.testing.assert_array_equal(np.stack([packed >> 16, (packed >> 8) & 255, packed & 255], 1),
                                      scene.rgb[order_want])
        assert cloud.header.frame_id == "map"

        info = infos[-1]
        np.testing.assert_array_equal(info.k.reshape(3, 3)[[0, 1, 0, 1], [0, 1, 2, 2]], K)
        assert (info.width, info.height, info.header.frame_id) == (320, 240, "camera_optical_frame")

        tf_attachments = recorder.attachments(table["/tf"])
        if form == "rmw_zenoh":
            parsed = [unpack_attachment(a) for a in tf_attachments]
            assert [seq for seq, _, _ in parsed] == list(range(1, len(parsed) + 1))
            assert len({gid for _, _, gid in parsed}) == 1
            assert all(abs(t - time.time_ns()) < 60e9 for _, t, _ in parsed)
            tokens = [str(r.ok.key_expr) for r in router.liveliness().get("@ros2_lv/4/**", timeout=2) if r.ok]
            zid = node.zid
            assert f"@ros2_lv/4/{zid}/0/0/NN/%/%/kmvipe" in tokens
            for topic, msgtype, _ in _keys(cfg):
                hash_ = messages.type_hash(msgtype)
                assert any(t.startswith(f"@ros2_lv/4/{zid}/0/") and
                           t.endswith(f"/MP/%/%/kmvipe/{topic.replace('/', '%')}/"
                                      f"{msgtype.replace('/msg/', '::msg::dds_::')}_/{hash_}/::,10:,:,:,,")
                           for t in tokens), topic
        else:
            assert set(tf_attachments) == {None}
            assert sorted(table.values()) == ["kmvipe/camera_info", "kmvipe/map", "kmvipe/path", "tf"]
    finally:
        node.close()
        for bus in (bridge_bus, km):
            bus.close()
        router.close()


def _keys(cfg: Ros2Settings):
    from services.ros2.cli import key_table

    return key_table(cfg)


def test_a_long_path_is_sent_evenly_subsampled():
    from services.ros2.bridge import Bridge

    router, endpoint = ros_router()
    recorder = Recorder(router, "**")
    cfg = Ros2Settings(_env_file=None, form="bridge", axes="optical", path_max_poses=3)
    node = RosNode(cfg, RosZenohSettings(_env_file=None, mode="client", connect=[endpoint]))
    try:
        bridge = Bridge(cfg, node)
        poses = random_poses(5)
        bridge.handle_poses(Poses(STREAM, 4, 0, frame_seqs=np.arange(5), stamps_ns=np.arange(5) * 10, poses=poses))
        await_subscriber(node.session, "kmvipe/path")
        bridge.send_path()
        path = wait_for(lambda: recorder.messages("kmvipe/path", messages.PATH), what="the path")[0]
        assert [messages.time_ns(p.header.stamp) for p in path.poses] == [0, 20, 40]
        np.testing.assert_allclose([pose_of(p.pose.position, p.pose.orientation) for p in path.poses],
                                   poses[[0, 2, 4]], atol=1e-9)
    finally:
        node.close()
        router.close()
