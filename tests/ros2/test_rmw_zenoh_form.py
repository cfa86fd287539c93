"""rmw_zenoh's wire form, checked byte for byte against published examples.

Sources (ros2/rmw_zenoh):
* ``docs/design.md``, "Topic and Service name mapping to Zenoh key expressions": the key expression of the
  ``chatter`` topic of demo_nodes_cpp, with and without the ``/robot1`` namespace, and its type hash; "Graph Cache":
  the liveliness tokens of the ``listener`` node, its subscription and the ``talker``'s publisher; "Publishers":
  the attachment layout (int64 sequence number, int64 timestamp, GID length byte, 16-byte GID).
* ``rmw_zenoh_cpp/src/detail/attachment_helpers.cpp``: the attachment is written with zenoh's serializer
  (``serialize(int64); serialize(int64); serialize(std::array<uint8_t, 16>)``), reproduced here with zenoh's own
  Python serializer (``zenoh.ext.z_serialize``) as the independent reference.
* ``rmw_zenoh_cpp/src/detail/liveliness_utils.cpp``: ``qos_to_keyexpr`` leaves a field empty when it equals
  rmw_zenoh's default (``qos.cpp``: reliable, volatile, keep last, depth 42), and the GID is XXH3-128 of the token.
"""

from __future__ import annotations

import pytest
import zenoh
import zenoh.ext

from services.ros2 import messages as ros
from services.ros2.wire import (QoS, attachment, endpoint_token, entity_gid, node_token, parse_attachment,
                                topic_key)

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"


@pytest.mark.parametrize("distro", ["jazzy", "kilted"])
def test_type_hash_of_the_design_documents_example(distro):
    assert ros.typestore(distro).hash_rihs01("std_msgs/msg/String") == STRING_HASH


@pytest.mark.parametrize("namespace, topic, expected", [
    ("", "chatter", "0/chatter/std_msgs::msg::dds_::String_/" + STRING_HASH),
    ("", "/chatter", "0/chatter/std_msgs::msg::dds_::String_/" + STRING_HASH),
    ("/robot1", "chatter", "0/robot1/chatter/std_msgs::msg::dds_::String_/" + STRING_HASH),
])
def test_topic_key_expressions(namespace, topic, expected):
    type_hash = ros.typestore("jazzy").hash_rihs01("std_msgs/msg/String")
    assert topic_key("rmw_zenoh", topic, "std_msgs/msg/String", type_hash, 0, namespace) == expected


def test_bridge_keys_are_the_topic_names():
    assert topic_key("bridge", "/odom", "nav_msgs/msg/Odometry") == "odom"
    assert topic_key("bridge", "scan", "", namespace="/bot1") == "bot1/scan"


def test_liveliness_tokens_of_the_design_documents_examples():
    assert node_token(2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, "listener") == \
        "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    assert endpoint_token("MS", 2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, 10, "listener", "/chatter",
                          "std_msgs/msg/String", STRING_HASH, QoS(depth=10)) == \
        ("@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/"
         f"{STRING_HASH}/::,10:,:,:,,")
    assert endpoint_token("MP", 2, "8b20917502ee955ac4476e0266340d5c", 0, 10, "talker", "/chatter",
                          "std_msgs/msg/String", STRING_HASH, QoS(depth=7)) == \
        ("@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/"
         f"{STRING_HASH}/::,7:,:,:,,")


@pytest.mark.parametrize("qos, expected", [
    (QoS(depth=42), "::,:,:,:,,"),  # every field rmw_zenoh's default
    (QoS(durability="transient_local", depth=1), ":1:,1:,:,:,,"),  # nav2's amcl_pose
    (QoS(reliability="best_effort", depth=5), "2::,5:,:,:,,"),  # sensor data
    (QoS(history="keep_all", depth=42), "::2,:,:,:,,"),
])
def test_qos_keyexpr(qos, expected):
    assert qos.keyexpr() == expected


@pytest.mark.parametrize("sequence, stamp", [(1, 1_700_000_000_123_456_789), (2**40, 0), (-1, 5)])
def test_attachment_matches_zenohs_serializer(sequence, stamp):
    gid = bytes(range(200, 216))
    reference = zenoh.ext.z_serialize((zenoh.ext.Int64(sequence), zenoh.ext.Int64(stamp), gid)).to_bytes()
    ours = attachment(sequence, stamp, gid)
    assert ours == reference and len(ours) == 8 + 8 + 1 + 16
    assert parse_attachment(reference) == (sequence, stamp, gid)
    sequence_back, stamp_back, gid_back = zenoh.ext.z_deserialize(tuple[zenoh.ext.Int64, zenoh.ext.Int64, bytes],
                                                                  zenoh.ZBytes(ours))
    assert (int(sequence_back), int(stamp_back), bytes(gid_back)) == (sequence, stamp, gid)


def test_the_attachment_of_earlier_rmw_zenoh_releases():
    """Before ros2/rmw_zenoh#605 (Jazzy's 0.2.4) each field came after its name (``ze_serializer_serialize_str``)."""
    gid = bytes(range(200, 216))
    named = zenoh.ext.z_serialize(("sequence_number", zenoh.ext.Int64(7), "source_timestamp", zenoh.ext.Int64(-3),
                                   "source_gid", gid)).to_bytes()
    assert parse_attachment(named) == (7, -3, gid)
    for bad in (named.replace(b"source_gid", b"source_gie"), named[:-1], named + b"\x00"):
        with pytest.raises(ValueError):
            parse_attachment(bad)


def test_gid_is_xxh3_128_of_the_token_low_half_first():
    import xxhash

    token = "@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/1/MP/%/%/semloc/%amcl_pose/x/y/::,1:,:,:,,"
    digest = xxhash.xxh3_128(token.encode()).digest()  # canonical (big-endian) form: high 64 bits first
    assert entity_gid(token) == digest[8:][::-1] + digest[:8][::-1]
    assert entity_gid(token) != entity_gid(token + "x")


@pytest.mark.parametrize("bad", [b"", bytes(32), bytes(16) + b"\x10" + bytes(15), bytes(16) + b"\x0f" + bytes(16)])
def test_malformed_attachments_are_refused(bad):
    with pytest.raises(ValueError):
        parse_attachment(bad)


def test_a_topic_given_in_part_keeps_its_roles_qos():
    """``--set topics.image.name=...`` renames the image topic; its QoS stays the image role's (best effort, depth
    5), so the subscription's token says what the robot's camera publishes."""
    from services.config import build, from_sets
    from services.workers.ros2 import Ros2Config

    topics = build(Ros2Config, from_sets(["topics.image.name=/oak/rgb/image_raw", "topics.pose.depth=3"])).topics
    assert (topics.image.name, topics.image.qos()) == ("/oak/rgb/image_raw", QoS("best_effort", "volatile",
                                                                                   "keep_last", 5))
    assert (topics.pose.name, topics.pose.qos()) == ("/amcl_pose", QoS("reliable", "transient_local", "keep_last", 3))
    assert topics.odom == Ros2Config().topics.odom
