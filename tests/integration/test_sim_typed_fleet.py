"""The simulated typed sensors as real processes through a real router (issue 41): a robot with
``driver = "sim"`` for a ``LaserScan``, a 640x480 ``Image`` and a JPEG ``CompressedImage``
(no driver class of the team's), a CEDDP that receives every sample (0 lost, 0 decode
errors), ``topic echo`` printing a scan, and ``record`` writing all three as sensor_msgs CDR
that mcap_ros2 decodes: the JPEG to a 640x480 picture."""

from __future__ import annotations

import json
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

from tests.integration.fleet import Process
from tests.support import free_port

pytestmark = pytest.mark.integration
SCAN, IMAGE, JPEG = (
    "sensor_msgs/msg/LaserScan",
    "sensor_msgs/msg/Image",
    "sensor_msgs/msg/CompressedImage",
)


def tool(cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "arpz", *args], cwd=cwd, capture_output=True, text=True, timeout=60
    )


def test_a_robots_simulated_scan_and_images_reach_the_ceddp_echo_and_a_recording(
    tmp_path: Path,
) -> None:
    simplejpeg = pytest.importorskip("simplejpeg")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    (tmp_path / "ceddp.toml").write_text(
        f'listen = ["{endpoint}"]\nsummary_json = "summary.json"\nrrd = "ceddp.rrd"\n'
        "metrics_period_s = 0.2\n"
    )
    (tmp_path / "robot.toml").write_text(
        f'robot_id = "robot1"\nconnect = ["{endpoint}"]\nstats_period_s = 0.2\n'
        f'[[sensors]]\nname = "scan"\ntype = "{SCAN}"\nrate_hz = 10\n'
        f'[[sensors]]\nname = "camera"\ntype = "{IMAGE}"\nrate_hz = 2\n'
        f'[[sensors]]\nname = "jpeg"\ntype = "{JPEG}"\nrate_hz = 5\noptions = {{ quality = 70 }}\n'
    )
    ceddp = Process("ceddp", ["-m", "arpz.ceddp", "--config", "ceddp.toml"], tmp_path)
    try:
        ceddp.wait_for("ready on")
        robot = Process("robot1", ["-m", "arpz.robot", "--config", "robot.toml"], tmp_path)
        try:
            robot.wait_for("running (3 sensors)")
            echo = tool(tmp_path, "topic", "echo", "/robot1/scan", "--connect", endpoint,
                        "--count", "1", "--json")  # fmt: skip
            assert echo.returncode == 0, echo.stderr
            scan = json.loads(echo.stdout.splitlines()[0])["message"]
            assert scan["type"] == SCAN
            assert len(scan["message"]["ranges"]) == 360
            assert scan["message"]["range_max"] == 12.0
            record = tool(tmp_path, "record", "--connect", endpoint, "--out", "sim.mcap",
                          "--duration", "3")  # fmt: skip
            assert record.returncode == 0, record.stderr
            assert robot.interrupt() == 0, robot.output()
        finally:
            robot.kill()
        assert ceddp.interrupt() == 0, ceddp.output()
    finally:
        ceddp.kill()

    summary = json.loads((tmp_path / "summary.json").read_text())
    robot1 = summary["robots"]["robot1"]
    assert robot1["decode_errors"] == 0
    for topic in ("scan", "camera", "jpeg"):
        row = robot1["topics"][topic]
        assert row["received"] == row["sent"] > 0, (topic, row)
        assert row["lost"] == row["decode_errors"] == row["driver_errors"] == 0, (topic, row)
        assert row["oversize"] == 0, (topic, row)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        from mcap_ros2.reader import read_ros2_messages

        seen: dict[str, int] = {}
        for message in read_ros2_messages(str(tmp_path / "sim.mcap")):
            topic, ros = message.channel.topic, message.ros_msg
            seen[topic] = seen.get(topic, 0) + 1
            if topic == "/robot1/scan":
                assert len(ros.ranges) == 360 and ros.range_max == 12.0
                assert ros.angle_increment == pytest.approx(2 * 3.14159265 / 360)
            elif topic == "/robot1/camera":
                assert (ros.width, ros.height, ros.encoding) == (640, 480, "rgb8")
                assert len(ros.data) == 640 * 480 * 3
            elif topic == "/robot1/jpeg":
                assert ros.format == "jpeg"
                assert simplejpeg.decode_jpeg(bytes(ros.data)).shape == (480, 640, 3)
    for topic in ("/robot1/scan", "/robot1/camera", "/robot1/jpeg"):
        assert seen.get(topic, 0) > 0, (topic, seen)
