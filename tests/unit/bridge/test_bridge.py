"""The bridge over the in-memory transport: a robot's announcement and samples out as ROS 2
messages, ROS 2 commands in as arpz commands, and bad input counted, never raised."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import pytest
from rosbags.typesys import Stores, get_typestore

from arpz.bridge import rmw_zenoh as rz
from arpz.bridge.__main__ import load, parse_args
from arpz.bridge.bridge import Bridge
from arpz.bridge.commands import CONVERTERS, command_value
from arpz.bridge.naming import command_key_expr, topic_name
from arpz.bridge.type_hash import type_hash
from arpz.channel import Reader, Writer
from arpz.core import keys
from arpz.core.config import (
    ROS2_COMMAND_TYPES,
    CeddpConfig,
    ConfigError,
    Ros2Config,
    from_dict,
    load_toml,
)
from arpz.core.messages import COMMAND_DECODER, Announce, Sample, TopicInfo, encode
from arpz.core.traffic import COMMAND_QOS, REPORT_QOS, SENSOR_QOS
from arpz.transport.memory import MemoryBus, MemoryTransport
from tests.support import wait_until

FLEET = "f"
STORE = get_typestore(Stores.ROS2_JAZZY)  # the ROS 2 side decodes with rosbags directly


def test_default_topic_names_and_overrides() -> None:
    config = Ros2Config(topics={"*/front": "/{robot}/camera/image_raw", "r2/lidar": "/laser"})
    assert topic_name(config, "robot1", "lidar", "lidar") == "/robot1/scan"
    assert topic_name(config, "robot1", "imu", "imu") == "/robot1/imu"
    assert topic_name(config, "robot1", "lidar_90", "lidar") == "/robot1/lidar_90"
    assert topic_name(config, "east-1", "front", "camera") == "/east_1/camera/image_raw"
    assert topic_name(config, "r2", "lidar", "lidar") == "/laser"
    assert topic_name(config, "7up", "pir", "pir") == "/_7up/motion"
    assert command_key_expr(0, "/{robot}/cmd_vel") == "0/*/cmd_vel/*/*"


def test_every_configurable_command_type_converts() -> None:
    assert set(CONVERTERS) == set(ROS2_COMMAND_TYPES)
    vector = STORE.types["geometry_msgs/msg/Vector3"]
    twist = STORE.types["geometry_msgs/msg/Twist"](
        linear=vector(x=0.5, y=9.0, z=9.0), angular=vector(x=9.0, y=9.0, z=-0.25)
    )
    assert command_value("geometry_msgs/msg/Twist", twist) == [0.5, -0.25]
    assert command_value("std_msgs/msg/Bool", STORE.types["std_msgs/msg/Bool"](data=True)) is True


def test_ros2_config_refuses_what_cannot_work() -> None:
    for bad in (
        {"domain_id": 300},
        {"node_name": "arpz-bridge"},
        {"topics": {"robot1": "/x"}},
        {"topics": {"*/lidar": "scan"}},
        {"commands": [{"topic": "/cmd_vel"}]},
        {"commands": [{"type": "TwistStamped"}]},
    ):
        with pytest.raises(ConfigError):
            from_dict(bad, Ros2Config, source="test")
    assert CeddpConfig().ros2.enabled is False


@pytest.fixture
def fleet() -> Iterator[tuple[Bridge, MemoryTransport, MemoryTransport]]:
    bus = MemoryBus()
    robot, ros, side = MemoryTransport(bus), MemoryTransport(bus), MemoryTransport(bus)
    bridge = Bridge(side, FLEET, CeddpConfig(fleet=FLEET), Ros2Config(enabled=True), zid="ab")
    bridge.start()
    try:
        yield bridge, robot, ros
    finally:
        bridge.close()


def test_samples_out_and_commands_in(
    fleet: tuple[Bridge, MemoryTransport, MemoryTransport],
) -> None:
    bridge, robot, ros = fleet
    tokens: set[str] = set()
    ros.watch_liveliness(rz.token_expr(0), lambda k, alive: tokens.add(k) if alive else None)
    scan_key = rz.topic_key(
        0, "/r1/scan", "sensor_msgs/msg/LaserScan", type_hash("sensor_msgs/msg/LaserScan")
    )
    got: list[tuple[bytes, bytes | None]] = []
    ros.subscribe(scan_key, lambda k, p, a: got.append((p, a)))
    commands: list[object] = []
    Reader(
        robot,
        keys.command_key(FLEET, "r1", "velocity"),
        COMMAND_QOS,
        lambda p, i: commands.append(COMMAND_DECODER.decode(p)),
    )
    announce = Announce(
        robot="r1",
        incarnation="i",
        sensors=[
            TopicInfo("lidar", "lidar", 10.0, "float"),
            TopicInfo("odd", "sonar", 1.0, "float"),
        ],
        commands=["velocity"],
    )
    Writer(robot, keys.announce_key(FLEET, "r1"), REPORT_QOS).write(encode(announce))
    wait_until(lambda: len(tokens) >= 3, what="node, publisher and subscription tokens")
    kinds = sorted(rz.parse_token(t).kind for t in tokens)
    assert kinds == ["MP", "MS", "NN"]
    assert bridge.counters.unknown_type == 1  # "sonar" has no ROS 2 type: counted, not raised

    lidar = Writer(robot, keys.sensor_key(FLEET, "r1", "lidar"), SENSOR_QOS)
    wait_until(lambda: lidar.matched_count > 0, what="the bridge's reader")
    lidar.write(encode(Sample("r1:i", 1, 1_000_000_123, 1.25)), stamp_ns=1_000_000_123)
    lidar.write(encode(Sample("r1:i", 2, 1_000_000_456, math.nan)), stamp_ns=1_000_000_456)
    wait_until(lambda: len(got) == 2, what="two LaserScans")
    message = STORE.deserialize_cdr(got[0][0], "sensor_msgs/msg/LaserScan")
    assert list(message.ranges) == [1.25] and message.header.frame_id == "r1/lidar"
    assert (message.header.stamp.sec, message.header.stamp.nanosec) == (1, 123)
    assert got[0][1] is not None and got[1][1] is not None
    first, second = rz.parse_attachment(got[0][1]), rz.parse_attachment(got[1][1])
    assert (first.sequence_number, second.sequence_number) == (1, 2)
    assert first.source_timestamp_ns == 1_000_000_123 and first.gid == second.gid

    twist_key = rz.topic_key(
        0, "/r1/cmd_vel", "geometry_msgs/msg/Twist", type_hash("geometry_msgs/msg/Twist")
    )
    vector = STORE.types["geometry_msgs/msg/Vector3"]
    twist = STORE.types["geometry_msgs/msg/Twist"](
        linear=vector(x=0.3, y=0.0, z=0.0), angular=vector(x=0.0, y=0.0, z=0.1)
    )
    cdr = bytes(STORE.serialize_cdr(twist, "geometry_msgs/msg/Twist"))
    ros.put(twist_key, cdr, attachment=rz.attachment(1, 5, bytes(16)))
    wait_until(lambda: len(commands) == 1, what="the command at the robot")
    assert commands[0].value == [0.3, 0.1]  # type: ignore[attr-defined]

    # bad input, each counted once, none raised
    ros.put(twist_key, b"\x00\x01\x00\x00\x05", attachment=rz.attachment(2, 5, bytes(16)))
    wrong = rz.topic_key(0, "/r1/cmd_vel", "std_msgs/msg/String", type_hash("std_msgs/msg/String"))
    ros.put(wrong, b"\x00\x01\x00\x00", attachment=None)
    ros.put(twist_key.replace("/r1/", "/r9/"), cdr)
    robot.put(keys.sensor_key(FLEET, "r1", "lidar"), b"not a channel sample")
    wait_until(
        lambda: (
            (bridge.counters.bad_cdr, bridge.counters.unknown_type, bridge.counters.unmapped)
            == (1, 2, 1)
        ),
        what="the bad input counted",
    )
    stats = bridge.stats()
    assert stats["topics"]["/r1/scan"]["published"] == 2
    assert stats["commands"]["/r1/cmd_vel"]["sent"] == 1
    assert stats["counters"]["commands_sent"] == 1


def test_the_ceddp_and_the_standalone_bridge_read_ros2_from_toml(tmp_path: Path) -> None:
    ceddp_toml = tmp_path / "ceddp.toml"
    ceddp_toml.write_text(
        '[ros2]\nenabled = true\ndomain_id = 5\n[ros2.topics]\n"*/front" = "/{robot}/cam"\n'
        '[[ros2.commands]]\ntopic = "/{robot}/speed"\ntype = "std_msgs/msg/Float64"\n'
        'command = "speed"\n'
    )
    ros2 = load_toml(ceddp_toml, CeddpConfig).ros2
    assert (ros2.enabled, ros2.domain_id, ros2.topics) == (True, 5, {"*/front": "/{robot}/cam"})
    assert [(c.topic, c.command) for c in ros2.commands] == [("/{robot}/speed", "speed")]
    bridge_toml = tmp_path / "bridge.toml"
    bridge_toml.write_text(
        'fleet = "east"\nconnect = ["tcp/10.0.0.1:7447"]\n[ros2]\ndomain_id = 4\n'
    )
    args = parse_args(["--config", str(bridge_toml), "--domain-id", "9"])
    config = load(args)
    assert (config.fleet, config.connect, config.ros2.domain_id) == (
        "east",
        ["tcp/10.0.0.1:7447"],
        9,
    )
    flags = load(parse_args(["--connect", "tcp/10.0.0.2:7447", "--fleet", "west"]))
    assert (flags.fleet, flags.connect, flags.ros2.enabled) == ("west", ["tcp/10.0.0.2:7447"], True)
    bridge_toml.write_text("[ros2]\ndomain_id = 999\n")
    with pytest.raises(ConfigError, match="domain_id"):
        load(parse_args(["--config", str(bridge_toml)]))
