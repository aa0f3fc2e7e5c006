"""The bridge's rclpy backend against a real ROS 2 node in another process, over Fast DDS.

A real CEDDP runs the bridge with ``[ros2] backend = "rclpy"``; a real robot runs the machine1
preset, a typed ``sensor_msgs/msg/LaserScan`` (``front_scan``, the simulated driver), a simulated
body in the hallway world and the services of tests/integration/service_handlers.py; the fleet's
sensors are BEST_EFFORT. The ROS 2 node (tests/integration/ros2_rclpy_peer.py, rclpy only) must
receive ``/robot1/scan``, ``/robot1/imu`` and ``/robot1/front_scan`` whose every field is what
the robot sent (matched by stamp against a witness reading the robot's own samples through the
reliable channel), see the bridge's QoS in ROS 2's graph, get ROS 2's own incompatible-QoS
events for a RELIABLE subscription and a BEST_EFFORT command publisher (and the bridge counts
its side of both), turn the robot with Twists on ``/robot1/cmd_vel``, and call
``/robot1/dock`` and ``/robot1/jammed`` as ``ros2 service call`` does.

Fast DDS discovers on one host: each test run takes a random ``ROS_DOMAIN_ID`` and
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, so parallel runs do not meet. Domains 30-100 keep
Fast DDS's ports (7400 + 250 x domain + ...) under Linux's ephemeral range, where the tests'
Zenoh routers take theirs.
"""

from __future__ import annotations

import json
import math
import os
import random
import threading
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pytest

from arpz.channel import Reader
from arpz.core import keys
from arpz.core.messages import MESSAGE_SAMPLE_DECODER, SAMPLE_DECODER, TELEMETRY_DECODER
from arpz.core.msgtypes import MessageTypes
from arpz.core.protocol.qos import ReliabilityPolicy
from arpz.core.traffic import REPORT_QOS, SENSOR_QOS
from tests.integration.fleet import Process, ceddp, robots, write_robot
from tests.integration.service_handlers import SERVICES
from tests.support import client

pytestmark = pytest.mark.integration

pytest.importorskip("rclpy", reason="the ros2 extra: pip install 'arpz[ros2]'")

REPO = Path(__file__).resolve().parents[2]
PEER = Path(__file__).with_name("ros2_rclpy_peer.py")
FLEET, ROBOT = "itest", "robot1"
SENSOR_BEST_EFFORT = msgspec.structs.replace(SENSOR_QOS, reliability=ReliabilityPolicy.BEST_EFFORT)
BEST_EFFORT_TOML = '[sensor_qos]\nreliability = "best_effort"\n'
ROBOT_EXTRA = (
    '[sim]\nworld = "hallway"\nbeam_rate_hz = 5.0\n'
    '[[sensors]]\nname = "front_scan"\ntype = "sensor_msgs/msg/LaserScan"\nrate_hz = 5.0\n'
    "options = { beams = 90, intensities = true }\n" + BEST_EFFORT_TOML + SERVICES
)
LASER_SCAN = "sensor_msgs/msg/LaserScan"
#: rmw's infinite duration, as ROS 2's graph reports a deadline never set
INFINITE_NS = 2**63 - 1


class Witness:
    """What the robot sent, as an arpz client reads it: readings and typed messages by stamp,
    and its headings with their stamps."""

    def __init__(self, transport: Any) -> None:
        self.types = MessageTypes()
        self.lock = threading.Lock()
        self.values: dict[tuple[str, int], Any] = {}
        self.headings: list[tuple[int, float]] = []
        self.readers = [
            Reader(
                transport,
                keys.sensor_key(FLEET, ROBOT, topic),
                SENSOR_BEST_EFFORT,
                self._on_sample,
            )
            for topic in ("lidar", "imu", "front_scan")
        ]
        self.readers.append(
            Reader(transport, keys.telemetry_key(FLEET, ROBOT), REPORT_QOS, self._on_pose)
        )

    def _on_sample(self, payload: bytes, info: Any) -> None:
        topic = info.key.rsplit("/", 1)[-1]
        if topic == "front_scan":  # the whole message, by its header's stamp
            typed = MESSAGE_SAMPLE_DECODER.decode(payload)
            value = self.types.to_builtins(self.types.decode(LASER_SCAN, typed.value))
            stamp = stamp_ns(value)
        else:
            sample = SAMPLE_DECODER.decode(payload)
            value, stamp = sample.value, sample.stamp_ns
        with self.lock:
            self.values[(topic, stamp)] = value

    def _on_pose(self, payload: bytes, info: Any) -> None:
        pose = TELEMETRY_DECODER.decode(payload)
        with self.lock:
            self.headings.append((pose.stamp_ns, pose.theta_rad))

    def value(self, topic: str, stamp_ns: int) -> Any:
        with self.lock:
            return self.values.get((topic, stamp_ns))

    def close(self) -> None:
        for reader in self.readers:
            reader.close()


def stamp_ns(message: dict[str, Any]) -> int:
    stamp = message["header"]["stamp"]
    return int(stamp["sec"]) * 1_000_000_000 + int(stamp["nanosec"])


def header(topic: str, message: dict[str, Any]) -> dict[str, Any]:
    return {"stamp": message["header"]["stamp"], "frame_id": f"{ROBOT}/{topic}"}


def test_a_ros2_node_on_fast_dds_sees_the_fleet_commands_it_and_calls_its_services(
    tmp_path: Path,
) -> None:
    domain = random.randint(30, 100)
    ros_env = {
        "ROS_DOMAIN_ID": str(domain),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]),
    }
    extra = f'[ros2]\nenabled = true\nbackend = "rclpy"\ndomain_id = {domain}\n' + BEST_EFFORT_TOML
    with ceddp(tmp_path, extra=extra, env=ros_env) as (server, endpoint):
        config = write_robot(
            tmp_path, ROBOT, endpoint, preset="machine1", rate_hz=20, extra=ROBOT_EXTRA
        )
        with robots(tmp_path, [config], env=ros_env), client(endpoint) as transport:
            witness = Witness(transport)
            out = tmp_path / "peer.json"
            peer = Process("ros2-peer", [str(PEER), "--out", str(out)], tmp_path, env=ros_env)
            try:
                assert peer.popen.wait(timeout=60) == 0, peer.output()
            finally:
                peer.kill()
                witness.close()
            result = json.loads(out.read_text())
            check_scans(result["received"]["scan"], witness)
            check_imu(result["received"]["imu"], witness)
            check_typed(result["received"]["front_scan"], witness)
            check_turned(witness, *result["turned_ns"])
        assert server.interrupt() == 0

    # QoS as ROS 2's graph shows the bridge's publishers: the fleet's sensor profile
    for topic, ros_type in (("scan", LASER_SCAN), ("imu", "sensor_msgs/msg/Imu")):
        (publisher,) = result["graph"][topic]
        assert publisher == {
            "node": "arpz_bridge",
            "type": ros_type,
            "reliability": "BEST_EFFORT",
            "durability": "VOLATILE",
            "liveliness": "AUTOMATIC",
            "deadline_ns": INFINITE_NS,
        }
    # ROS 2's own incompatible-QoS events: a RELIABLE subscription on the BEST_EFFORT /imu, a
    # BEST_EFFORT publisher on the bridge's RELIABLE /cmd_vel subscription
    roles = {(e["role"], e["policy"]) for e in result["events"]}
    assert roles == {
        ("subscription", "RMW_QOS_POLICY_RELIABILITY"),
        ("publisher", "RMW_QOS_POLICY_RELIABILITY"),
    }, result["events"]
    # ros2 service call /robot1/dock std_srvs/srv/Trigger, and a handler that raises
    services = result["services"]
    assert services["dock"] == {"success": True, "message": "docked"}
    assert services["jammed"]["success"] is False
    assert "the dock is blocked" in services["jammed"]["message"]

    summary = json.loads((tmp_path / "summary.json").read_text())
    bridge = summary["ros2"]
    counters = bridge["counters"]
    assert bridge["backend"] == "rclpy"
    assert counters["qos_incompatible"] >= 2, counters  # the bridge's side of both events
    assert counters["commands_sent"] >= 20 and counters["commands_write_failures"] == 0
    assert (counters["service_calls"], counters["service_answered"]) == (2, 1)
    assert bridge["services"]["/robot1/dock"]["answered"] == 1
    assert bridge["topics"]["/robot1/front_scan"]["type"] == LASER_SCAN
    assert "Traceback" not in server.output()


def matched(
    received: list[dict[str, Any]], witness: Witness, topic: str
) -> list[tuple[dict[str, Any], Any]]:
    """Each message received with what the robot sent for it (by stamp): at least 5. Others
    were sent before the witness matched, or lost on its best-effort reader."""
    pairs = [(m, witness.value(topic, stamp_ns(m))) for m in received]
    pairs = [(message, sent) for message, sent in pairs if sent is not None]
    assert len(pairs) >= 5, f"only {len(pairs)} of {len(received)} {topic} messages matched"
    return pairs


def check_scans(received: list[dict[str, Any]], witness: Witness) -> None:
    """Every field of the LaserScan of one arpz LIDAR reading (arpz.core.rosmsg)."""
    for message, value in matched(received, witness, "lidar"):
        assert message == {
            "header": header("lidar", message),
            "angle_min": 0.0,
            "angle_max": 0.0,
            "angle_increment": 0.0,
            "time_increment": 0.0,
            "scan_time": 0.0,
            "range_min": 0.0,
            "range_max": math.inf,
            "ranges": [float(np.float32(value))],
            "intensities": [],
        }


def check_imu(received: list[dict[str, Any]], witness: Witness) -> None:
    """Every field of the Imu of one arpz IMU reading: the vertical acceleration, orientation
    and angular velocity "not provided" (REP 145: covariance[0] = -1)."""
    not_provided = [-1.0] + [0.0] * 8
    for message, value in matched(received, witness, "imu"):
        assert message == {
            "header": header("imu", message),
            "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
            "orientation_covariance": not_provided,
            "angular_velocity": {"x": 0.0, "y": 0.0, "z": 0.0},
            "angular_velocity_covariance": not_provided,
            "linear_acceleration": {"x": 0.0, "y": 0.0, "z": value},
            "linear_acceleration_covariance": [0.0] * 9,
        }


def check_typed(received: list[dict[str, Any]], witness: Witness) -> None:
    """A typed topic: the whole message the robot's driver made, field for field."""
    for message, sent in matched(received, witness, "front_scan"):
        assert message == sent
        assert len(message["ranges"]) == len(message["intensities"]) == 90


def check_turned(witness: Witness, start_ns: int, end_ns: int) -> None:
    """The peer's Twists (1 rad/s for 2.5 s) turned the simulated body."""
    with witness.lock:
        during = [theta for stamp, theta in witness.headings if start_ns <= stamp <= end_ns + 5e8]
        before = [theta for stamp, theta in witness.headings if stamp < start_ns]
    assert before and during, "telemetry before and during the turn"
    turned = abs(math.remainder(during[-1] - before[-1], math.tau))
    assert turned >= 0.8, f"heading changed by {turned:.2f} rad only"
