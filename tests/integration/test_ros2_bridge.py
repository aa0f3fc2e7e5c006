"""The ROS 2 bridge against a stand-in ROS 2 node (tests/integration/ros2_peer.py), through a real
CEDDP router with real robot processes.

The robot runs the machine1 preset (LIDAR, IMU, ...), a 160x120 camera and a simulated body in
the hallway world. A witness arpz client reads the robot's own samples through the reliable
channel; the peer must receive LaserScan, Imu and Image messages whose fields are those readings
(matched by stamp), discovered from the bridge's liveliness tokens alone; the peer's Twist
commands must turn the simulated robot (its telemetry's heading changes); and the peer's service
client (rmw_zenoh's SC token, ``get`` with the request header attachment) must call the robot's
``dock`` and ``jammed`` services (tests/integration/service_handlers.py) through the bridge's SS
token and queryable, and get the responses with its sequence number and GID echoed.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from arpz.channel import FrameReader, Reader
from arpz.core import keys
from arpz.core.config import LARGE_SAMPLE_BYTES
from arpz.core.messages import LARGE_SAMPLE_DECODER, SAMPLE_DECODER, TELEMETRY_DECODER
from arpz.core.traffic import FRAMES_QOS, REPORT_QOS, SENSOR_QOS
from tests.integration.fleet import Process, ceddp, robots, write_robot
from tests.integration.ros2_peer import GID, SERVICE_HASHES, STORE, Ros2Peer, qos_fields
from tests.integration.service_handlers import SERVICES
from tests.support import client, wait_until

pytestmark = pytest.mark.integration

DOMAIN = 7
#: rmw_zenoh docs/design.md: the DDS type names in keys and tokens
LASER_SCAN = "sensor_msgs::msg::dds_::LaserScan_"
IMU = "sensor_msgs::msg::dds_::Imu_"
IMAGE = "sensor_msgs::msg::dds_::Image_"
TWIST = "geometry_msgs::msg::dds_::Twist_"
TRIGGER = "std_srvs/srv/Trigger"
REPO = Path(__file__).resolve().parents[2]
#: the robot imports its service handlers from tests.integration.service_handlers
ENV = {"PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
ROBOT_EXTRA = (
    '[sim]\nworld = "hallway"\nbeam_rate_hz = 5.0\n'
    '[[sensors]]\nname = "camera"\nkind = "camera"\nrate_hz = 4.0\n'
    "options = { width = 160, height = 120 }\n"
)
ROBOT_SERVICES = ROBOT_EXTRA + SERVICES


class Witness:
    """The robot's own readings and poses, as an arpz client reads them (by stamp)."""

    def __init__(self, transport: object) -> None:
        self.lock = threading.Lock()
        self.values: dict[tuple[str, int], object] = {}
        self.headings: list[float] = []
        fleet, robot = "itest", "robot1"
        self.readers = [
            Reader(transport, keys.sensor_key(fleet, robot, t), SENSOR_QOS, self._on_sample)  # type: ignore[arg-type]
            for t in ("lidar", "imu")
        ]
        self.readers.append(
            Reader(transport, keys.telemetry_key(fleet, robot), REPORT_QOS, self._on_pose)  # type: ignore[arg-type]
        )
        self.frames = FrameReader(
            transport,  # type: ignore[arg-type]
            keys.frames_key(fleet, robot, "camera"),
            FRAMES_QOS,
            self._on_frame,
            max_frame_bytes=LARGE_SAMPLE_BYTES,
        )

    def _on_sample(self, payload: bytes, info: object) -> None:
        sample = SAMPLE_DECODER.decode(payload)
        topic = info.key.rsplit("/", 1)[-1]  # type: ignore[attr-defined]
        with self.lock:
            self.values[(topic, sample.stamp_ns)] = sample.value

    def _on_frame(self, payload: bytes, info: object) -> None:
        sample = LARGE_SAMPLE_DECODER.decode(payload)
        with self.lock:
            self.values[("camera", sample.stamp_ns)] = sample.value

    def _on_pose(self, payload: bytes, info: object) -> None:
        pose = TELEMETRY_DECODER.decode(payload)
        with self.lock:
            self.headings.append(pose.theta_rad)

    def value(self, topic: str, stamp_ns: int) -> object:
        with self.lock:
            return self.values.get((topic, stamp_ns))

    def close(self) -> None:
        for reader in self.readers:
            reader.close()
        self.frames.close()


def stamp_ns(message: object) -> int:
    stamp = message.header.stamp  # type: ignore[attr-defined]
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def test_a_ros2_node_sees_the_fleet_and_drives_a_simulated_robot(tmp_path: Path) -> None:
    extra = f"[ros2]\nenabled = true\ndomain_id = {DOMAIN}\n"
    with ceddp(tmp_path, extra=extra) as (server, endpoint):
        config = write_robot(
            tmp_path, "robot1", endpoint, preset="machine1", rate_hz=20, extra=ROBOT_SERVICES
        )
        with (
            robots(tmp_path, [config], env=ENV),
            client(endpoint) as transport,
            Ros2Peer(endpoint, domain=DOMAIN) as peer,
        ):
            witness = Witness(transport)
            try:
                # discovery: the bridge's node and its entities, from liveliness tokens only
                wanted = [
                    ("MP", "/robot1/scan"),
                    ("MP", "/robot1/imu"),
                    ("MP", "/robot1/image_raw"),
                ]
                wanted.append(("MS", "/robot1/cmd_vel"))
                wait_until(
                    lambda: all(peer.find(k, t) for k, t in wanted),
                    timeout_s=15,
                    what="the bridged topics' tokens",
                )
                nodes = [e.node for e in peer.graph() if e.kind == "NN"]
                assert "arpz_bridge" in nodes
                scan, imu, image, cmd = (peer.find(k, t) for k, t in wanted)
                assert scan and imu and image and cmd
                assert (scan.dds_type, imu.dds_type, image.dds_type) == (LASER_SCAN, IMU, IMAGE)
                assert cmd.dds_type == TWIST
                qos = qos_fields(scan.qos)
                assert qos["reliability"] == "" and qos["durability"] == ""  # RELIABLE, VOLATILE
                assert qos["depth"] == str(SENSOR_QOS.depth)
                # the topic tool shows the bridged topics too (issue 19)
                tool = [sys.executable, "-m", "arpz", "topic", "list", "--fleet", "itest"]
                listed = subprocess.run(
                    [*tool, "--connect", endpoint, "--json"],
                    capture_output=True,
                    text=True,
                    timeout=60,
                )
                assert listed.returncode == 0, listed.stderr
                ros2 = json.loads(listed.stdout)["ros2"]
                assert {
                    "node": "/arpz_bridge",
                    "topic": "/robot1/scan",
                    "type": "sensor_msgs/msg/LaserScan",
                    "role": "publisher",
                } in [{k: r[k] for k in ("node", "topic", "type", "role")} for r in ros2], ros2
                for entity in (scan, imu, image):
                    peer.subscribe(entity)
                wait_until(
                    lambda: (
                        len(peer.messages("/robot1/scan")) >= 10
                        and len(peer.messages("/robot1/imu")) >= 10
                        and len(peer.messages("/robot1/image_raw")) >= 3
                    ),
                    timeout_s=15,
                    what="LaserScan, Imu and Image samples",
                )
                time.sleep(0.3)  # the witness's last samples
                check_scans(peer, witness)
                check_imu(peer, witness)
                check_images(peer, witness)

                # commands: turn on the spot; the simulated body's heading must follow
                key = peer.publisher("/robot1/cmd_vel", "geometry_msgs/msg/Twist")
                assert key.split("/")[-1] == cmd.type_hash, "the peer's own hash = the bridge's"
                wait_until(lambda: len(witness.headings) >= 3, what="telemetry")
                before = witness.headings[-1]
                deadline = time.monotonic() + 6
                turned = 0.0
                while time.monotonic() < deadline and turned < 0.8:
                    peer.publish(key, "geometry_msgs/msg/Twist", peer.twist(0.0, 1.0))
                    time.sleep(0.05)
                    turned = abs(math.remainder(witness.headings[-1] - before, math.tau))
                assert turned >= 0.8, f"heading changed by {turned:.2f} rad only"

                # bad input: another type on the command topic, and bytes that are not CDR
                wrong = peer.publisher("/robot1/cmd_vel", "std_msgs/msg/String")
                peer.publish(wrong, "std_msgs/msg/String", string_message("spin"))
                peer.session.put(key, b"\x00\x01\x00\x00\x01")

                check_services(peer)
            finally:
                witness.close()
            assert server.interrupt() == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    bridge = summary["ros2"]
    counters = bridge["counters"]
    assert counters["published"] > 0 and counters["commands_sent"] > 0
    assert counters["unknown_type"] >= 1 and counters["bad_cdr"] >= 1
    assert bridge["topics"]["/robot1/scan"]["type"] == "sensor_msgs/msg/LaserScan"
    assert bridge["commands"]["/robot1/cmd_vel"]["sent"] == counters["commands_sent"]
    assert bridge["services"]["/robot1/dock"] == {
        "robot": "robot1",
        "service": "dock",
        "type": TRIGGER,
        "calls": 1,
        "answered": 1,
        "failed": 0,
    }
    assert bridge["services"]["/robot1/jammed"]["failed"] == 1
    assert (counters["service_calls"], counters["service_answered"]) == (2, 1)
    # the CEDDP's service caller made the calls, and the robot served them
    calls = summary["services"]["robot1"]
    assert calls["dock"]["caller"]["ok"] == 1 and calls["jammed"]["caller"]["failed"] == 1
    # the robot acted on them as on any command of its reliable downlink
    assert "Traceback" not in server.output()


def string_message(text: str) -> object:
    return STORE.types["std_msgs/msg/String"](data=text)


def check_services(peer: Ros2Peer) -> None:
    """The robot's services as rmw_zenoh services: an SS token each, a call each."""
    wait_until(
        lambda: peer.find("SS", "/robot1/dock") and peer.find("SS", "/robot1/jammed"),
        timeout_s=10,
        what="the bridge's SS tokens of the robot's services",
    )
    server = peer.find("SS", "/robot1/dock")
    assert server is not None and server.node == "arpz_bridge"
    assert server.dds_type == "std_srvs::srv::dds_::Trigger_"
    assert server.type_hash == SERVICE_HASHES[TRIGGER], "ROS 2's own hash of the service type"
    assert qos_fields(server.qos)["depth"] == "10"  # the services' default QoS
    request = STORE.types[f"{TRIGGER}_Request"](structure_needs_at_least_one_member=0)
    key = peer.client("/robot1/dock", TRIGGER)
    assert key == server.data_key
    reply = peer.call(key, TRIGGER, request)
    assert reply.response is not None, "no response from /robot1/dock"
    assert (reply.response.success, reply.response.message) == (True, "docked")
    assert (reply.sequence_number, reply.gid) == (1, GID), "the request header echoed"
    assert abs(reply.source_timestamp_ns - time.time_ns()) < 10e9
    assert reply.key == key
    # a handler that raises: Trigger's failure response (success False and why)
    jammed = peer.call(peer.client("/robot1/jammed", TRIGGER), TRIGGER, request)
    assert jammed.response is not None and jammed.response.success is False
    assert "the dock is blocked" in jammed.response.message, jammed.response.message


def check_scans(peer: Ros2Peer, witness: Witness) -> None:
    received = peer.messages("/robot1/scan")
    matched = 0
    for item in received:
        message = item.message
        assert message.header.frame_id == "robot1/lidar"
        assert item.source_timestamp_ns == stamp_ns(message)
        value = witness.value("lidar", stamp_ns(message))
        if value is None:
            continue  # sent before the witness matched
        matched += 1
        assert len(message.ranges) == 1
        assert float(message.ranges[0]) == float(np.float32(value))  # type: ignore[arg-type]
    assert matched >= 5, f"only {matched} of {len(received)} scans matched a robot reading"
    seqs = [r.sequence_number for r in received]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), "attachment seqs are consecutive"
    assert len({r.gid for r in received}) == 1


def check_imu(peer: Ros2Peer, witness: Witness) -> None:
    received = peer.messages("/robot1/imu")
    matched = 0
    for item in received:
        value = witness.value("imu", stamp_ns(item.message))
        if value is None:
            continue
        matched += 1
        assert item.message.linear_acceleration.z == value
    assert matched >= 5, f"only {matched} of {len(received)} Imu messages matched"


def check_images(peer: Ros2Peer, witness: Witness) -> None:
    received = peer.messages("/robot1/image_raw")
    matched = 0
    for item in received:
        message = item.message
        assert (message.width, message.height, message.encoding) == (160, 120, "rgb8")
        frame = witness.value("camera", stamp_ns(message))
        if frame is None:
            continue
        matched += 1
        assert bytes(message.data) == frame
    assert matched >= 1, f"none of {len(received)} images matched a camera frame"


def test_the_standalone_bridge_joins_a_running_fleet(tmp_path: Path) -> None:
    with ceddp(tmp_path) as (_, endpoint):
        config = write_robot(tmp_path, "robot2", endpoint, preset="machine1", rate_hz=20)
        with robots(tmp_path, [config]), Ros2Peer(endpoint, domain=3) as peer:
            bridge = Process(
                "bridge",
                [
                    *("-m", "arpz.bridge", "--connect", endpoint, "--fleet", "itest"),
                    *("--domain-id", "3", "--duration", "6"),
                ],
                tmp_path,
            )
            try:
                bridge.wait_for("arpz bridge: running")
                wait_until(
                    lambda: peer.find("MP", "/robot2/scan") is not None,
                    timeout_s=10,
                    what="the standalone bridge's /robot2/scan token",
                )
                scan = peer.find("MP", "/robot2/scan")
                assert scan is not None
                peer.subscribe(scan)
                wait_until(lambda: len(peer.messages("/robot2/scan")) >= 5, what="scans")
                assert bridge.popen.wait(timeout=15) == 0
            finally:
                bridge.kill()
            stats = json.loads(bridge.output()[bridge.output().index("{") :])
            assert stats["counters"]["published"] >= 5
            assert stats["topics"]["/robot2/scan"]["published"] >= 5
