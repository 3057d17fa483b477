"""Key expressions, liveliness tokens, attachments and type hashes of the ROS 2 bridge, against the examples
ros2/rmw_zenoh's docs/design.md gives and the hashes ROS 2 itself prints (``ros2 topic info -v``)."""
from __future__ import annotations

import pytest
import zenoh
import zenoh.ext as zext

from services.ros2.core import messages
from services.ros2.core.names import (
    Qos, check_topic, dds_type_name, endpoint_token, mangle, msgtype_of_key, node_token, pack_attachment,
    topic_key, topic_selector, unpack_attachment,
)

STRING = "std_msgs/msg/String"
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"  # rmw_zenoh docs/design.md
ZID = "aac3178e146ba6f1fc6e6a4085e77f21"  # the session id of design.md's examples

# what `ros2 topic info -v` prints on Jazzy for the types the bridge speaks
GOLDEN = {
    "tf2_msgs/msg/TFMessage": "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
    "nav_msgs/msg/Path": "RIHS01_1957a5bb3cee5da65c4e52e52b65a93df227efce4c20f8458b36e73066ca334b",
    "sensor_msgs/msg/PointCloud2": "RIHS01_9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5",
    "sensor_msgs/msg/CameraInfo": "RIHS01_b3dfd68ff46c9d56c80fd3bd4ed22c7a4ddce8c8348f2f59c299e73118e7e275",
    "sensor_msgs/msg/Image": "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
    "sensor_msgs/msg/CompressedImage": "RIHS01_15640771531571185e2efc8a100baf923961a4d15d5569652e6cb6691e8e371a",
    STRING: STRING_HASH,
}


@pytest.mark.parametrize("msgtype", sorted(GOLDEN))
def test_rosbags_computes_the_type_hashes_ros2_prints(msgtype):
    assert messages.type_hash(msgtype) == GOLDEN[msgtype]


def test_humble_keys_carry_no_type_hash():
    assert messages.type_hash("sensor_msgs/msg/Image", "humble") == "TypeHashNotSupported"


def test_data_keys_are_design_md_examples():
    assert topic_key("rmw_zenoh", "/chatter", STRING, messages.type_hash(STRING)) == (
        "0/chatter/std_msgs::msg::dds_::String_/" + STRING_HASH)
    assert topic_key("rmw_zenoh", "/robot1/chatter", STRING, STRING_HASH, domain_id=0) == (
        "0/robot1/chatter/std_msgs::msg::dds_::String_/" + STRING_HASH)
    assert topic_key("rmw_zenoh", "/tf", "tf2_msgs/msg/TFMessage", "h", domain_id=3) == (
        "3/tf/tf2_msgs::msg::dds_::TFMessage_/h")


def test_bridge_form_keys_are_the_topic_without_its_leading_slash():
    assert topic_key("bridge", "/chatter", STRING, STRING_HASH) == "chatter"
    assert topic_key("bridge", "/bot1/camera/image_raw", "sensor_msgs/msg/Image", "x") == "bot1/camera/image_raw"
    assert topic_selector("bridge", "/camera/image_raw") == "camera/image_raw"


def test_a_subscription_selector_takes_every_type_and_hash_of_its_topic():
    assert topic_selector("rmw_zenoh", "/camera/image_raw", domain_id=5) == "5/camera/image_raw/*/*"
    key = topic_key("rmw_zenoh", "/camera/image_raw", messages.COMPRESSED, "TypeHashNotSupported", 5)
    assert msgtype_of_key(key) == messages.COMPRESSED
    assert msgtype_of_key("camera/image_raw") is None


def test_liveliness_tokens_are_design_md_examples():
    assert node_token(2, ZID, 0, "listener") == f"@ros2_lv/2/{ZID}/0/0/NN/%/%/listener"
    assert endpoint_token("MS", 2, ZID, 0, 10, "listener", "/chatter", STRING, STRING_HASH, Qos(depth=10)) == (
        f"@ros2_lv/2/{ZID}/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/{STRING_HASH}/::,10:,:,:,,")
    assert endpoint_token("MP", 2, "8b20917502ee955ac4476e0266340d5c", 0, 10, "talker", "/chatter", STRING,
                          STRING_HASH, Qos(depth=7)) == (
        "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/"
        f"{STRING_HASH}/::,7:,:,:,,")


def test_qos_chunk_leaves_rmw_zenoh_defaults_empty():
    assert Qos(depth=42).chunk() == "::,:,:,:,,"  # RELIABLE, VOLATILE, KEEP_LAST 42: all defaults
    assert Qos(depth=10, reliable=False, transient_local=True).chunk() == "2:1:,10:,:,:,,"


def test_names_are_checked_and_mangled():
    assert mangle("/a/b") == "%a%b"
    assert dds_type_name("sensor_msgs/msg/Image") == "sensor_msgs::msg::dds_::Image_"
    for bad in ("camera/image", "/camera//image", "/camera/", "/1cam", "/cam era"):
        with pytest.raises(ValueError, match="fully qualified"):
            check_topic(bad)
    with pytest.raises(ValueError):
        dds_type_name("Image")


def test_attachment_is_what_the_zenoh_serializer_of_rmw_zenoh_writes():
    gid = bytes(range(16, 32))
    ours = pack_attachment(7, 1_700_000_000_123_456_789, gid)
    reference = zext.z_serialize((zext.Int64(7), zext.Int64(1_700_000_000_123_456_789),
                                  [zext.UInt8(b) for b in gid])).to_bytes()
    assert ours == reference and len(ours) == 33
    seq, t_ns, got = zext.z_deserialize(tuple[zext.Int64, zext.Int64, list[zext.UInt8]], zenoh.ZBytes(ours))
    assert (seq, t_ns, bytes(got)) == (7, 1_700_000_000_123_456_789, gid)
    assert unpack_attachment(ours) == (7, 1_700_000_000_123_456_789, gid)
    with pytest.raises(ValueError):
        unpack_attachment(ours[:-1])
    with pytest.raises(ValueError):
        pack_attachment(1, 2, b"short")
