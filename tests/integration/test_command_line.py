"""The command line as a new user meets it, with real processes (issue 18): a server started on
"any free port" prints the port robots need, and a robot that cannot reach its server says which
endpoint and for how long it tried, within the --duration it was given."""

from __future__ import annotations

import re
import time
from pathlib import Path

import pytest

from tests.integration.fleet import Process, free_port
from tests.support import wait_until

pytestmark = pytest.mark.integration

ROBOT = ["-m", "arpz.robot", "--robot-id", "robot1", "--preset", "machine3"]


def test_a_ceddp_on_port_0_prints_the_port_a_robot_then_reaches(tmp_path: Path) -> None:
    rrd = ["--rrd", str(tmp_path / "c.rrd")]
    ceddp = Process(
        "ceddp",
        ["-m", "arpz.ceddp", "--listen", "tcp/127.0.0.1:0", "--fleet", "portzero", *rrd],
        tmp_path,
    )
    robot = None
    try:
        ceddp.wait_for("ready on")
        line = next(text for text in ceddp.lines if "ready on" in text)
        match = re.search(r"--connect (tcp/127\.0\.0\.1:(\d+)) --fleet portzero", line)
        assert match and match.group(2) != "0", line
        robot = Process(
            "robot1",
            [*ROBOT, "--fleet", "portzero", "--connect", match.group(1)],
            tmp_path,
        )
        robot.wait_for("running")
        wait_until(lambda: "robot1" in ceddp.output(), timeout_s=20, what="the CEDDP sees robot1")
        assert robot.interrupt() == 0
        assert ceddp.interrupt() == 0
    finally:
        if robot is not None:
            robot.kill()
        ceddp.kill()


def test_an_unreachable_server_is_named_within_the_duration(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    start = time.monotonic()
    robot = Process(
        "robot1",
        [*ROBOT, "--connect", endpoint, "--duration", "2"],
        tmp_path,
    )
    try:
        wait_until(lambda: robot.popen.poll() is not None, timeout_s=20, what="the robot exits")
        elapsed = time.monotonic() - start
        out = robot.output()
        assert robot.popen.returncode == 1, out
        assert f"arpz robot: error: cannot open a Zenoh client session on {endpoint}" in out
        assert "tried for 2 s" in out, out
        # interpreter start-up plus the 2 s asked for, not the 30 s connect timeout
        assert elapsed < 15, elapsed
    finally:
        robot.kill()


def test_a_bad_endpoint_is_a_configuration_error_naming_the_flag(tmp_path: Path) -> None:
    robot = Process(
        "robot1", ["-m", "arpz.robot", "--robot-id", "r1", "--connect", "foo"], tmp_path
    )
    try:
        wait_until(lambda: robot.popen.poll() is not None, timeout_s=20, what="the robot exits")
        out = robot.output()
        assert robot.popen.returncode == 2, out
        assert "connect[0] 'foo'" in out and "PROTOCOL/ADDRESS" in out, out
        assert "(given by --connect)" in out, out
        assert "Json5" not in out and ".rs" not in out, out
    finally:
        robot.kill()
