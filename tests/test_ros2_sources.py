"""ROS 2 images into ingest: a live topic published in ROS form on a loopback Zenoh router (rmw_zenoh keys with
their attachment, or zenoh-bridge-ros2dds keys) and bags written here with rosbags (MCAP and SQLite, as a folder
or a single file) come out of ``open_source`` as frames with the messages' stamps and pixels."""
from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest

from services.common.errors import SourceError
from services.ingest.sources import BadFrame, SourceFrame, open_source
from services.ros2.core import messages
from services.ros2.core.names import pack_attachment, topic_key
from tests.test_ros2_bridge import await_subscriber, ros_router

RNG = np.random.default_rng(3)
T0 = 1_700_000_000_000_000_000


def frames_of(n: int, h: int = 12, w: int = 16) -> list[np.ndarray]:
    return [RNG.integers(0, 256, (h, w, 3)).astype(np.uint8) for _ in range(n)]


def ros_env(monkeypatch, endpoint: str, form: str, **extra) -> None:
    env = {"KMVIPE_ROS2_FORM": form, "KMVIPE_ROS2_DOMAIN_ID": "3", "KMVIPE_ROS2_ZENOH_MODE": "client",
           "KMVIPE_ROS2_ZENOH_CONNECT": json.dumps([endpoint]), "KMVIPE_ROS2_QUEUE": "16",
           "KMVIPE_ROS2_IDLE_TIMEOUT_S": "1", "KMVIPE_ROS2_FIRST_MESSAGE_TIMEOUT_S": "10", **extra}
    for name, value in env.items():
        monkeypatch.setenv(name, value)


def message_of(msgtype: str, rgb: np.ndarray, t_ns: int):
    if msgtype == messages.IMAGE:
        return messages.image_message(rgb, t_ns, "camera", encoding="bgr8")
    return messages.compressed_message(rgb, t_ns, "camera", fmt="png")


def _graph_tokens_until(router, part: str, within_s: float = 10.0) -> list[str]:
    """The ROS graph's liveliness tokens, asked again until one contains ``part`` or ``within_s`` passed (the
    node's token can arrive before its subscription's on a loaded machine)."""
    deadline = time.monotonic() + within_s
    while True:
        tokens = [str(r.ok.key_expr) for r in router.liveliness().get("@ros2_lv/3/**", timeout=2) if r.ok]
        if any(part in t for t in tokens) or time.monotonic() > deadline:
            return tokens
        time.sleep(0.1)


@pytest.mark.parametrize("form", ["rmw_zenoh", "bridge"])
@pytest.mark.parametrize("topic, msgtype", [("/camera/image_raw", messages.IMAGE),
                                            ("/camera/image_raw/compressed", messages.COMPRESSED)])
def test_a_live_ros_topic_is_a_source(monkeypatch, form, topic, msgtype):
    router, endpoint = ros_router()
    ros_env(monkeypatch, endpoint, form)
    try:
        source = open_source(f"ros2:{topic}")
        assert source.live and source.name == f"ros2:{topic}"
        key = topic_key(form, topic, msgtype, messages.type_hash(msgtype), domain_id=3)
        await_subscriber(router, key)
        publisher = router.declare_publisher(key)
        images, stamps = frames_of(5), [T0 + 33_333_333 * i for i in range(5)]
        gid = bytes(range(16))
        for i, (rgb, t_ns) in enumerate(zip(images, stamps)):
            payload = messages.serialize(message_of(msgtype, rgb, t_ns))
            attachment = pack_attachment(i + 1, t_ns, gid) if form == "rmw_zenoh" else None
            publisher.put(payload, attachment=attachment)
            if i == 1:  # a malformed sample is one bad frame; the stream goes on
                publisher.put(b"\x00\x01\x00\x00garbage", attachment=attachment)
        if form == "rmw_zenoh":  # the subscription is in the ROS graph
            tokens = _graph_tokens_until(router, "/MS/%/%/kmvipe/" + topic.replace("/", "%") + "/")
            assert any("/MS/%/%/kmvipe/" + topic.replace("/", "%") + "/" in t for t in tokens), tokens
        got = list(source.frames())  # ends once the topic is quiet for idle_timeout_s
    finally:
        router.close()
    assert [type(f) for f in got] == [SourceFrame] * 2 + [BadFrame] + [SourceFrame] * 3
    good = [f for f in got if isinstance(f, SourceFrame)]
    assert [f.t_ns for f in good] == stamps
    for frame, rgb in zip(good, images):
        np.testing.assert_array_equal(frame.rgb, rgb)


def test_a_silent_topic_stops_with_what_to_check(monkeypatch):
    router, endpoint = ros_router()
    ros_env(monkeypatch, endpoint, "rmw_zenoh", KMVIPE_ROS2_FIRST_MESSAGE_TIMEOUT_S="0.3")
    try:
        with pytest.raises(SourceError, match=r"no image on ROS 2 topic /cam/image.*KMVIPE_ROS2_ZENOH_CONNECT"):
            list(open_source("ros2:/cam/image").frames())
    finally:
        router.close()


def write_bag(path, storage: str, topics: dict[str, str], n: int = 4):
    """A rosbag2 bag with ``n`` images on each of ``topics`` (name → type) and a String topic; each image is
    recorded 1 ms after its header stamp. Returns {topic: [(stamp, rgb), ...]}."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    store, written = messages.typestore(), {}
    with Writer(path, version=9, storage_plugin=StoragePlugin[storage]) as writer:
        chatter = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=store)
        writer.write(chatter, T0, messages.serialize(store.types["std_msgs/msg/String"](data="hello")))
        for topic, msgtype in topics.items():
            conn = writer.add_connection(topic, msgtype, typestore=store)
            written[topic] = [(T0 + 100_000_000 * i, rgb) for i, rgb in enumerate(frames_of(n))]
            for stamp, rgb in written[topic]:
                writer.write(conn, stamp + 1_000_000, messages.serialize(message_of(msgtype, rgb, stamp)))
    return written


@pytest.mark.parametrize("storage, suffix", [("MCAP", ".mcap"), ("SQLITE3", ".db3")])
def test_a_bag_is_a_source_folder_or_file(tmp_path, storage, suffix):
    bag = tmp_path / "run1"
    written = write_bag(bag, storage, {"/camera/image_raw": messages.IMAGE,
                                       "/camera/image_raw/compressed": messages.COMPRESSED})
    for spec in (bag, bag / f"run1{suffix}"):
        for topic in written:
            source = open_source(str(spec), topic=topic)
            # the topic's messages over the bag's span (the String at T0 to the last image, recorded 1 ms late)
            assert not source.live and source.fps == pytest.approx(3 / 0.301)
            got = list(source.frames())
            assert [f.index for f in got] == [0, 1, 2, 3]
            assert [f.t_ns for f in got] == [stamp for stamp, _ in written[topic]]  # header stamps, not log times
            for frame, (_, rgb) in zip(got, written[topic]):
                np.testing.assert_array_equal(frame.rgb, rgb)


def test_a_bags_only_image_topic_needs_no_name_and_two_need_one(tmp_path):
    written = write_bag(tmp_path / "one", "MCAP", {"/cam/image": messages.IMAGE}, n=2)
    got = list(open_source(str(tmp_path / "one")).frames())
    assert [f.t_ns for f in got] == [stamp for stamp, _ in written["/cam/image"]]
    write_bag(tmp_path / "two", "MCAP", {"/a/image": messages.IMAGE, "/b/image": messages.COMPRESSED}, n=1)
    with pytest.raises(SourceError, match=r"several image topics \(/a/image \(Image\), /b/image "
                                          r"\(CompressedImage\)\).*--topic"):
        open_source(str(tmp_path / "two"))
    with pytest.raises(SourceError, match="has no image topic /chatter"):
        open_source(str(tmp_path / "two"), topic="/chatter")
    write_bag(tmp_path / "none", "SQLITE3", {})
    with pytest.raises(SourceError, match=r"no sensor_msgs/Image or CompressedImage topic \(topics: /chatter\)"):
        open_source(str(tmp_path / "none"))


def test_ingest_streams_the_bag_topic_its_settings_name(tmp_path):
    """``KMVIPE_INGEST_TOPIC`` (``kmvipe run --topic``) picks the topic the ingest service streams."""
    from services.common import keys
    from services.common.schema import Credit, Eos, Frame
    from services.ingest.config import IngestSettings
    from services.ingest.service import run
    from tests.query_api_fixtures import bus_pair, wait_for

    written = write_bag(tmp_path / "bag", "MCAP", {"/a/image": messages.IMAGE, "/b/image": messages.COMPRESSED}, n=3)
    cfg = IngestSettings(_env_file=None, source=str(tmp_path / "bag"), topic="/b/image", stream="rosbag",
                         encoding="raw", wait_for_consumer_s=10)
    ingest, consumer = bus_pair("ingest", "features")
    box = consumer.inbox({keys.topic("rosbag", keys.FRAME): [Frame], keys.topic("rosbag", keys.EOS): [Eos]})
    stop, done = threading.Event(), []
    worker = threading.Thread(target=lambda: done.append(run(cfg, ingest, stop)), daemon=True)
    worker.start()
    got = []
    try:
        def eos():  # grant credit for everything until the stream ends
            consumer.publish(keys.topic("rosbag", keys.CREDIT), Credit("rosbag", 100, 0, consumer="test"))
            while (d := box.get(0.05)) is not None:
                got.append(d.msg)
            return any(isinstance(m, Eos) for m in got)

        wait_for(eos, what="the end of the bag's stream")
    finally:
        stop.set()
        worker.join(5)
        for bus in (consumer, ingest):
            bus.close()
    frames = [m for m in got if isinstance(m, Frame)]
    assert [f.t_ns for f in frames] == [stamp for stamp, _ in written["/b/image"]]
    for frame, (_, rgb) in zip(frames, written["/b/image"]):
        np.testing.assert_array_equal(frame.image, rgb)
