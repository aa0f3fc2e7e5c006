"""The live Foxglove view of a running fleet: a real CEDDP with ``foxglove_port`` and two real
robots (LIDAR and IMU among their sensors) through its router, and a WebSocket client speaking
the Foxglove protocol as the Foxglove app does (tests/foxglove_ws.py): the robots' topics and
metrics are advertised with their schemas, and subscribed scan and IMU messages arrive and
decode to the robots' readings."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import pytest

from tests.foxglove_ws import FoxgloveClient, descriptor_fields, packed_doubles, protobuf_fields
from tests.integration.fleet import ceddp, robots, write_robot
from tests.support import free_port

pytestmark = pytest.mark.integration

ROBOTS = ("robot1", "robot2")


def test_foxglove_shows_every_robots_scan_imu_and_metrics(tmp_path: Path) -> None:
    port = free_port()
    with ceddp(tmp_path, extra=f"foxglove_port = {port}\n") as (server, endpoint):
        configs = [
            write_robot(tmp_path, robot, endpoint, preset="machine1", rate_hz=20)
            for robot in ROBOTS
        ]
        with robots(tmp_path, configs), FoxgloveClient("127.0.0.1", port) as client:
            wanted = {f"/{r}/{t}" for r in ROBOTS for t in ("lidar", "imu", "pir", "metrics")}
            wanted.add("/ceddp/metrics")
            channels = client.wait_for_topics(wanted, timeout_s=15)
            for robot in ROBOTS:
                assert channels[f"/{robot}/lidar"]["schemaName"] == "foxglove.LaserScan"
                assert channels[f"/{robot}/imu"]["schemaName"] == "sensor_msgs/msg/Imu"
                assert channels[f"/{robot}/pir"]["schemaName"] == "std_msgs/msg/Bool"
            scans = [f"/{r}/lidar" for r in ROBOTS]
            imus = [f"/{r}/imu" for r in ROBOTS]
            metrics = ["/robot1/metrics", "/ceddp/metrics"]
            topics = scans + imus + metrics
            subscribed = client.subscribe([int(channels[t]["id"]) for t in topics])
            topic_of = {
                s: next(t for t, c in channels.items() if c["id"] == cid)
                for s, cid in subscribed.items()
            }
            got: dict[str, list[tuple[int, bytes]]] = {}
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline and not (
                set(got) == set(topics) and all(len(got[t]) >= 3 for t in scans + imus)
            ):
                message = client.poll(deadline)
                if message is not None:
                    topic = topic_of[message.subscription]
                    got.setdefault(topic, []).append((message.log_time_ns, message.payload))
            received_at = time.time_ns()
        assert server.interrupt() == 0, server.output()
    assert set(got) == set(topics), sorted(got)

    fields = descriptor_fields(channels["/robot1/lidar"]["schema"], "LaserScan")
    for topic in scans:
        robot = topic.split("/")[1]
        for log_time_ns, payload in got[topic]:
            scan = protobuf_fields(payload)
            (distance,) = packed_doubles(scan[fields["ranges"]][0])
            assert 0.0 < distance < 50.0 and math.isfinite(distance)  # metres, one beam
            assert scan[fields["frame_id"]] == [f"{robot}/lidar".encode()]
            assert 0 < received_at - log_time_ns < 30e9  # the robot's stamp of the reading
    for topic in imus:
        for _, payload in got[topic]:
            imu = json.loads(payload)
            assert imu["header"]["frame_id"] == topic.strip("/")
            assert 0.0 < imu["linear_acceleration"]["z"] < 4 * 9.81  # the magnitude, m/s^2
            assert imu["orientation_covariance"][0] == -1.0  # ROS 2's "not provided"

    robot_metrics = json.loads(got["/robot1/metrics"][-1][1])
    assert robot_metrics["topics"]["lidar"]["rate_hz"] >= 0.0  # the dashboard's per-topic rows
    assert "cpu_percent" in robot_metrics
    assert json.loads(got["/ceddp/metrics"][-1][1])["ingest_load"] >= 0.0

    summary = json.loads((tmp_path / "summary.json").read_text())
    view = summary["foxglove"]
    assert view["logged"] >= sum(len(v) for v in got.values())
    assert view["unshowable"] == 0
    assert view["dropped"] == 0  # two robots at 20 Hz never fill the view's queue
