"""Golden tests of rmw_zenoh's byte layouts (arpz/bridge/rmw_zenoh.py).

Sources of the examples, each cited where used:
- DESIGN: ros2/rmw_zenoh ``docs/design.md`` (commit 99a6a2bd10b949052f4f12c5854825dc005e95a5,
  https://github.com/ros2/rmw_zenoh/blob/rolling/docs/design.md), sections "Topic and Service
  name mapping to Zenoh key expressions", "Graph Cache" and "Publishers".
- QOS_CPP: ros2/rmw_zenoh ``rmw_zenoh_cpp/src/detail/qos.cpp`` (commit 7efeee2b) for the
  default QoS, ``liveliness_utils.cpp`` (commit 3411fdec) for ``qos_to_keyexpr``.
- ZENOH_SERIALIZER: ``zenoh.ext.z_serialize``, the Zenoh serializer that rmw_zenoh's
  ``AttachmentData::serialize_to_zbytes`` uses (``attachment_helpers.cpp``, commit 534747dc).
"""

from __future__ import annotations

import struct

import pytest
import zenoh
from zenoh.ext import Int64, UInt8, z_deserialize, z_serialize

from arpz.bridge import rmw_zenoh as rz
from arpz.core.protocol.qos import DurabilityPolicy, HistoryPolicy, QosProfile, ReliabilityPolicy

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
ADD_TWO_INTS_HASH = "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"

# DESIGN, "Topic and Service name mapping to Zenoh key expressions"
CHATTER_KEY = f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
ROBOT1_CHATTER_KEY = f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
ADD_TWO_INTS_KEY = f"2/add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/{ADD_TWO_INTS_HASH}"

# DESIGN, "Graph Cache": the demo_nodes_cpp examples
LISTENER_NODE = "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
LISTENER_SUB = (
    "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/"
    f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,10:,:,:,,"
)
TALKER_PUB = (
    "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
    f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,"
)
SERVER = (
    "@ros2_lv/2/f9980ee0495eaafb3e38f0d19e2eae12/0/10/SS/%/%/add_two_ints_server/"
    f"%add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/{ADD_TWO_INTS_HASH}/::,10:,:,:,,"
)
CLIENT = (
    "@ros2_lv/2/e1dc8d1b45ae8717fce78689cc655685/0/10/SC/%/%/add_two_ints_client/"
    f"%add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/{ADD_TWO_INTS_HASH}/::,10:,:,:,,"
)


def test_key_expressions_are_those_of_the_design_document() -> None:
    assert rz.topic_key(0, "/chatter", "std_msgs/msg/String", STRING_HASH) == CHATTER_KEY
    assert rz.topic_key(0, "/robot1/chatter", "std_msgs/msg/String", STRING_HASH) == (
        ROBOT1_CHATTER_KEY
    )
    assert rz.topic_key(
        2, "/add_two_ints", "example_interfaces/srv/AddTwoInts", ADD_TWO_INTS_HASH
    ) == (ADD_TWO_INTS_KEY)
    parsed = rz.parse_topic_key(ROBOT1_CHATTER_KEY)
    assert parsed == rz.TopicKey(0, "/robot1/chatter", "std_msgs/msg/String", STRING_HASH)
    assert rz.parse_topic_key("arpz/itest/robot/r1/sensor/lidar") is None
    assert rz.parse_topic_key("0/chatter/std_msgs::msg::dds_::String_/md5") is None


def test_dds_type_names_both_ways() -> None:
    assert rz.dds_type_name("sensor_msgs/msg/LaserScan") == "sensor_msgs::msg::dds_::LaserScan_"
    assert rz.ros_type_name("geometry_msgs::msg::dds_::Twist_") == "geometry_msgs/msg/Twist"
    for bad in ("String", "a/b", "std_msgs//String"):
        with pytest.raises(rz.WireError):
            rz.dds_type_name(bad)
    with pytest.raises(rz.WireError):
        rz.ros_type_name("std_msgs::msg::String")


@pytest.mark.parametrize("token", [LISTENER_NODE, LISTENER_SUB, TALKER_PUB, SERVER, CLIENT])
def test_the_design_documents_tokens_parse_and_are_written_back_byte_for_byte(token: str) -> None:
    entity = rz.parse_token(token)
    assert entity.token() == token


def test_a_token_says_what_the_design_document_says_it_says() -> None:
    sub = rz.parse_token(LISTENER_SUB)
    assert (sub.domain_id, sub.zid, sub.node_id, sub.entity_id) == (
        2,
        "aac3178e146ba6f1fc6e6a4085e77f21",
        "0",
        "10",
    )
    assert (sub.kind, sub.enclave, sub.namespace, sub.node) == ("MS", "/", "/", "listener")
    assert (sub.topic, sub.ros_type, sub.type_hash) == (
        "/chatter",
        "std_msgs/msg/String",
        STRING_HASH,
    )
    assert sub.qos == rz.RmwQos(depth=10)
    talker = rz.parse_token(TALKER_PUB)
    assert talker.qos == rz.RmwQos(depth=7)  # demo_nodes_cpp's talker: KeepLast(7)
    # the document's tokens are of domain 2 (its key examples of domain 0)
    assert talker.data_key == "2" + CHATTER_KEY[1:]


def test_the_bridges_own_tokens() -> None:
    node = rz.Entity(
        domain_id=0,
        zid="ab12",
        node_id="0",
        entity_id="0",
        kind=rz.NODE,
        namespace="/",
        node="arpz_bridge",
    )
    assert node.token() == "@ros2_lv/0/ab12/0/0/NN/%/%/arpz_bridge"
    scan = rz.Entity(
        domain_id=0,
        zid="ab12",
        node_id="0",
        entity_id="3",
        kind=rz.PUBLISHER,
        namespace="/",
        node="arpz_bridge",
        topic="/robot1/scan",
        ros_type="sensor_msgs/msg/LaserScan",
        type_hash="RIHS01_" + "0" * 64,
        qos=rz.qos_from_profile(QosProfile(depth=10, deadline_s=0.25)),
    )
    assert scan.token() == (
        "@ros2_lv/0/ab12/0/3/MP/%/%/arpz_bridge/%robot1%scan/sensor_msgs::msg::dds_::LaserScan_/"
        "RIHS01_" + "0" * 64 + "/::,10:0,250000000:,:,,"
    )
    assert scan.data_key == "0/robot1/scan/sensor_msgs::msg::dds_::LaserScan_/RIHS01_" + "0" * 64
    assert rz.parse_token(scan.token()) == scan
    assert len(scan.gid) == 16 and scan.gid != node.gid
    # rmw_zenoh's own derivation (simplified_xxhash3.cpp of ros2/rmw_zenoh at bfc065f, compiled
    # with g++ and run on this token) printed these bytes: ROS 2 tools that compare GIDs agree
    assert scan.gid.hex() == "8e76a79f70fbacaa53f233222352b126"


def test_gid_is_rmw_zenohs_xxh3_128_of_the_token() -> None:
    # rmw_zenoh's simplified_xxhash3.cpp printed these for a talker's token, the empty string
    # and a 300-byte token (the "long input" path of XXH3, past 240 bytes)
    talker = (
        "@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/11/MP/%/%/talker/%chatter/"
        "std_msgs::msg::dds_::String_/"
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,10:,:,:,,"
    )
    expected = {
        talker: "96d0f5ee9e9c8224c29b0eb3e2dfa8f4",
        "": "7f498d4624c30160d8984701d306aa99",
        "x" * 300: "5435c87d60b4d1a57abcd72aea375212",
    }
    for token, gid in expected.items():
        assert rz.gid_of_token(token).hex() == gid


def test_qos_defaults_are_rmw_zenohs_and_encode_as_empty_fields() -> None:
    # QOS_CPP: KEEP_LAST 42, RELIABLE, VOLATILE, infinite deadline/lifespan/lease, AUTOMATIC
    assert rz.DEFAULT_QOS.encode() == "::,:,:,:,,"
    assert rz.RmwQos.decode("::,:,:,:,,") == rz.DEFAULT_QOS
    every = rz.RmwQos(
        reliability=rz.BEST_EFFORT,
        durability=rz.TRANSIENT_LOCAL,
        history=rz.KEEP_ALL,
        depth=5,
        deadline=(1, 500),
        lifespan=(2, 0),
        liveliness=rz.MANUAL_BY_TOPIC,
        lease=(3, 7),
    )
    assert every.encode() == "2:1:2,5:1,500:2,0:3,3,7"
    assert rz.RmwQos.decode(every.encode()) == every
    for bad in ("", "::,10:,:,:", ":::::", "x::,:,:,:,,", "::,10,1:,:,:,,"):
        with pytest.raises(rz.WireError):
            rz.RmwQos.decode(bad)


def test_arpz_profiles_map_to_ros2_qos() -> None:
    sensor = rz.qos_from_profile(QosProfile())
    assert sensor == rz.RmwQos(depth=10)
    command = rz.qos_from_profile(QosProfile(depth=10, lifespan_s=0.5))
    assert command.lifespan == (0, 500_000_000) and command.deadline == rz.INFINITE
    best = rz.qos_from_profile(
        QosProfile(reliability=ReliabilityPolicy.BEST_EFFORT, history=HistoryPolicy.KEEP_ALL)
    )
    assert (best.reliability, best.history) == (rz.BEST_EFFORT, rz.KEEP_ALL)
    # the bridge keeps no publication cache, so it never offers TRANSIENT_LOCAL
    latched = rz.qos_from_profile(QosProfile(durability=DurabilityPolicy.TRANSIENT_LOCAL))
    assert latched.durability == rz.VOLATILE
    assert rz.qos_from_profile(None).reliability == rz.BEST_EFFORT  # arpz's plain mode


def test_the_attachment_is_the_one_zenohs_serializer_writes() -> None:
    # DESIGN "Publishers": int64 LE sequence number, int64 LE timestamp, 1 length byte (16),
    # 16 GID bytes; ZENOH_SERIALIZER writes (int64, int64, std::array<uint8_t,16>) the same way
    gid = bytes(range(0xA0, 0xB0))
    ours = rz.attachment(42, 1_700_000_000_123_456_789, gid)
    theirs = z_serialize((Int64(42), Int64(1_700_000_000_123_456_789), [UInt8(b) for b in gid]))
    assert ours == theirs.to_bytes()
    assert len(ours) == rz.ATTACHMENT_BYTES == 33
    assert ours[:8] == struct.pack("<q", 42) and ours[16] == 16
    seq, stamp, back = z_deserialize(tuple[Int64, Int64, list[UInt8]], zenoh.ZBytes(ours))
    assert (seq, stamp, bytes(back)) == (42, 1_700_000_000_123_456_789, gid)
    assert rz.parse_attachment(ours) == rz.Attachment(42, 1_700_000_000_123_456_789, gid)
    with pytest.raises(rz.WireError):
        rz.parse_attachment(ours[:-1])
    with pytest.raises(rz.WireError):
        rz.attachment(1, 2, b"short")


@pytest.mark.parametrize(
    "bad",
    [
        "@ros2_lv/0/z/0/0/NN/%/%",  # too short
        "@ros2_lv/x/z/0/0/NN/%/%/n",  # domain not a number
        "@ros2_lv/0/z/0/0/XX/%/%/n",  # unknown kind
        "@other/0/z/0/0/NN/%/%/n",
        "@ros2_lv/0/z/0/0/NN/%/%/n/extra",
        LISTENER_SUB.replace("/::,10:,:,:,,", ""),  # no QoS
        LISTENER_SUB.replace("::,10:,:,:,,", "::,ten:,:,:,,"),
    ],
)
def test_a_malformed_token_is_a_wire_error(bad: str) -> None:
    with pytest.raises(rz.WireError):
        rz.parse_token(bad)


def test_graph_records_for_the_topic_tool() -> None:
    records, bad = rz.graph_records([LISTENER_NODE, LISTENER_SUB, TALKER_PUB, SERVER, "junk"])
    assert bad == 1
    assert [(r.node, r.topic, r.ros_type, r.role, r.qos.depth) for r in records] == [
        ("/listener", "/chatter", "std_msgs/msg/String", "subscription", 10),
        ("/talker", "/chatter", "std_msgs/msg/String", "publisher", 7),
    ]
    assert records[1].qos.describe().startswith("RELIABLE, VOLATILE, KEEP_LAST (7)")
    assert rz.token_expr(0) == "@ros2_lv/0/**"
