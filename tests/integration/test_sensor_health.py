"""Health that never goes silent (issue 41), with real robot and CEDDP processes through the
CEDDP's real router: a robot whose only driver raises on every read, and a sensor whose every
reading is NaN, are flagged by the doctor, ``topic list``, the status page, ``/metrics`` and the
summary; a restart with another sensor set shows only its current topics; a second process with
a robot_id in use is refused at start, and one that ran while the first was cut off is found
when the link heals, its samples dropped and counted."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import urllib.request
from pathlib import Path
from typing import Any

import pytest

from tests.integration.fleet import Process, ceddp, settle, write_robot
from tests.support import free_port, wait_until

pytestmark = pytest.mark.integration

FLEET = "itest"

DRIVERS = """
from arpz.robot.sensors.base import SensorDriver


class Raises(SensorDriver):
    kind = "dht11"

    def read(self, now_s):
        raise OSError("[Errno 5] Input/output error")
"""


def status(port: int) -> dict[str, Any]:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/status", timeout=5) as response:
        return dict(json.loads(response.read()))


def metrics(port: int) -> str:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as response:
        return str(response.read().decode())


def robot_row(port: int, robot: str) -> dict[str, Any] | None:
    return next((r for r in status(port)["robots"] if r["robot"] == robot), None)


def tool(*args: str, timeout_s: float = 30) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "arpz", *args], capture_output=True, text=True, timeout=timeout_s
    )


def start(tmp: Path, name: str, config: Path) -> Process:
    """A robot process that can import the test's own drivers (``labdrivers``)."""
    args = ["-m", "arpz.robot", "--config", str(config)]
    return Process(name, args, tmp, env={"PYTHONPATH": str(tmp)})


def test_failing_sensors_are_flagged_everywhere_and_a_restart_starts_afresh(
    tmp_path: Path,
) -> None:
    (tmp_path / "labdrivers.py").write_text(DRIVERS)
    (tmp_path / "nan.csv").write_text("t_s,value\n0,nan\n0.5,inf\n")
    port = free_port()
    with ceddp(tmp_path, extra=f"web_port = {port}\n") as (server, endpoint):
        # robot1: a preset, and a sensor that only ever reads NaN or infinity
        nan_sensor = (
            '[[sensors]]\nname = "temp"\nkind = "dht11"\nrate_hz = 10\ndriver = "replay"\n'
            'trace = "nan.csv"\noptions = { loop = true }\n'
        )
        first = write_robot(
            tmp_path, "robot1", endpoint, preset="machine2", rate_hz=20, extra=nan_sensor
        )
        # robot2: its only driver raises on every read (the robot)
        broken = tmp_path / "robot2.toml"
        broken.write_text(
            f'robot_id = "robot2"\nfleet = "{FLEET}"\nconnect = ["{endpoint}"]\n'
            "stats_period_s = 0.2\n"
            '[[sensors]]\nname = "probe"\nkind = "dht11"\nrate_hz = 5\n'
            'driver = "labdrivers:Raises"\n'
        )
        robot1, robot2 = start(tmp_path, "robot1", first), start(tmp_path, "robot2", broken)
        try:
            robot1.wait_for("running")
            robot2.wait_for("running")

            def flagged() -> bool:
                rows = {r["robot"]: r for r in status(port)["robots"]}
                return all(
                    robot in rows and rows[robot]["silent_sensors"] == [topic]
                    for robot, topic in (("robot1", "temp"), ("robot2", "probe"))
                )

            wait_until(flagged, timeout_s=20, what="both failing sensors on the status page")
            rows = {r["robot"]: r for r in status(port)["robots"]}
            probe = {t["topic"]: t for t in rows["robot2"]["topics"]}["probe"]
            assert probe["received"] == 0 and probe["driver_errors"] > 0, probe
            assert probe["last_driver_error"] == "OSError: [Errno 5] Input/output error"
            temp = {t["topic"]: t for t in rows["robot1"]["topics"]}["temp"]
            assert temp["driver_errors"] > 0 and temp["last_driver_error"].startswith(
                "value refused: a dht11 driver returned"
            ), temp
            assert rows["robot1"]["received"] > 0  # its other sensors work
            text = metrics(port)
            assert 'arpz_robot_driver_errors_total{robot="robot2",topic="probe"}' in text
            assert 'arpz_robot_sensor_silent{robot="robot2",topic="probe"} 1.0' in text

            doctor = tool("doctor", "--connect", endpoint, "--fleet", FLEET, "--json", "-")
            report = json.loads(doctor.stdout)
            checks = {c["check"]: c for c in report["checks"]}
            assert doctor.returncode == 1, doctor.stdout
            assert checks["sensors"]["level"] == "FAIL", checks["sensors"]
            for name in ("robot1/temp", "robot2/probe"):
                assert name in checks["sensors"]["message"], checks["sensors"]
            assert checks["robots"]["level"] == "WARN", checks["robots"]
            assert checks["delivery"]["level"] == "WARN", checks["delivery"]

            listing = tool("topic", "list", "--connect", endpoint, "--fleet", FLEET)
            assert listing.returncode == 0, listing.stderr
            row = next(line for line in listing.stdout.splitlines() if "/robot2/probe" in line)
            assert "NO READING" in row and "driver errors" in row, listing.stdout
            assert robot2.interrupt() == 0, robot2.output()
            # one line per cause every 10 s, and the run's last word on the sensor
            logged = [line for line in robot2.lines if "sensor probe: driver error #" in line]
            assert logged and len(logged) <= 2, logged
            assert any("reads gave no reading in this run" in line for line in robot2.lines)

            # robot1 restarted with another sensor set: only its new topic is live
            before = robot_row(port, "robot1")
            assert before is not None
            assert robot1.interrupt() == 0, robot1.output()
            second = write_robot(
                tmp_path,
                "robot1",
                endpoint,
                preset="machine2",
                extra='[[sensors]]\nname = "front"\nkind = "lidar"\nrate_hz = 20\n',
                top="",
            )
            text = second.read_text().replace('preset = "machine2"\n', "")
            second.write_text(text)
            robot1 = start(tmp_path, "robot1", second)
            robot1.wait_for("running")

            def restarted() -> bool:
                row = robot_row(port, "robot1")
                return (
                    row is not None
                    and row["incarnation"] != before["incarnation"]
                    and [t["topic"] for t in row["topics"]] == ["front"]
                    and row["received"] > 0
                )

            wait_until(restarted, timeout_s=15, what="robot1's new incarnation on the page")
            now = robot_row(port, "robot1")
            assert now is not None
            assert now["previous"]["incarnations"] == 1
            assert now["previous"]["received"] >= before["received"] > now["received"] > 0
            assert now["silent_sensors"] == [] and now["driver_errors"] == 0
            text = metrics(port)
            samples = [
                line
                for line in text.splitlines()
                if line.startswith('arpz_robot_samples_sent_total{robot="robot1"')
            ]
            assert len(samples) == 1 and 'topic="front"' in samples[0], samples
            assert 'arpz_robot_previous_samples_received_total{robot="robot1"}' in text
            assert robot1.interrupt() == 0, robot1.output()
        finally:
            robot1.kill()
            robot2.kill()
        assert server.interrupt() == 0, server.output()
    summary = json.loads((tmp_path / "summary.json").read_text())
    probe_row = summary["robots"]["robot2"]["topics"]["probe"]
    assert probe_row["produced"] == probe_row["driver_errors"] > 0, probe_row
    for robot, row in summary["robots"].items():
        for topic, t in row["topics"].items():
            if topic == "hello":
                continue
            assert t["produced"] == (
                t["sent"] + t["held_back"] + t["write_failures"] + t["driver_errors"]
            ), (robot, topic, t)
        for incarnation, counts in row["incarnations"].items():
            assert counts["reconciled"] is True, (robot, incarnation, counts)


LEASE = "{ transport: { link: { tx: { lease: 2000, keep_alive: 4 } } } }\n"


def test_a_robot_id_in_use_is_refused_and_one_found_running_twice_is_flagged(
    tmp_path: Path,
) -> None:
    port = free_port()
    zenoh = tmp_path / "short-lease.json5"
    zenoh.write_text(LEASE)
    with ceddp(tmp_path, extra=f"web_port = {port}\n") as (server, endpoint):
        # a short lease: the router lets a frozen robot go within 2 s (Zenoh's is 10 s)
        config = write_robot(
            tmp_path,
            "robot1",
            endpoint,
            preset="machine2",
            rate_hz=20,
            top=f'zenoh_config = "{zenoh.as_posix()}"\n',
        )
        first = start(tmp_path, "robot1-first", config)
        second: Process | None = None
        try:
            first.wait_for("running")
            wait_until(
                lambda: (row := robot_row(port, "robot1")) is not None and row["received"] > 0,
                what="robot1 reporting",
            )
            # a second process with the same robot_id is refused at start, saying why
            refused = start(tmp_path, "robot1-refused", config)
            try:
                code = refused.popen.wait(timeout=30)
            finally:
                refused.kill()
            assert code == 2, refused.output()
            assert "robot_id 'robot1' is in use: another process runs as robot1" in (
                refused.output()
            )
            incarnation = robot_row(port, "robot1")["incarnation"]  # type: ignore[index]

            # the first one frozen until the router drops it; a second starts meanwhile
            first.popen.send_signal(signal.SIGSTOP)
            wait_until(
                lambda: not robot_row(port, "robot1")["alive"],  # type: ignore[index]
                timeout_s=15,
                what="the router to drop the frozen robot1",
            )
            second = start(tmp_path, "robot1-second", config)
            second.wait_for("running")
            wait_until(
                lambda: robot_row(port, "robot1")["incarnation"] != incarnation,  # type: ignore[index]
                what="the second process followed as a restart",
            )
            first.popen.send_signal(signal.SIGCONT)  # the link heals: both run

            def flagged() -> bool:
                row = robot_row(port, "robot1")
                return (
                    row is not None
                    and row["incarnation"] == incarnation
                    and len(row["duplicates"]) == 1
                    and row["duplicate_dropped"] > 0
                )

            wait_until(flagged, timeout_s=20, what="the duplicate found, its samples dropped")
            doctor = tool("doctor", "--connect", endpoint, "--fleet", FLEET, "--json", "-")
            checks = {c["check"]: c for c in json.loads(doctor.stdout)["checks"]}
            assert doctor.returncode == 1 and checks["robot ids"]["level"] == "FAIL", checks
            assert "two processes run with one robot_id: robot1" in checks["robot ids"]["message"]
            assert 'arpz_robot_duplicate_processes{robot="robot1"} 1.0' in metrics(port)
            settle(0.5)
            assert second.interrupt() == 0, second.output()
            assert first.interrupt() == 0, first.output()
        finally:
            first.kill()
            if second is not None:
                second.kill()
        assert server.interrupt() == 0, server.output()
    summary = json.loads((tmp_path / "summary.json").read_text())
    row = summary["robots"]["robot1"]
    assert row["incarnation"] == incarnation and len(row["duplicates"]) == 1, row["duplicates"]
    events = [e for e in summary["events"] if "two processes run as robot1" in e]
    assert len(events) == 1, summary["events"]
    assert row["duplicate_dropped"] > 0
    for name, counts in row["incarnations"].items():
        assert counts["reconciled"] is True, (name, counts)
    dropped = [c["duplicate_dropped"] for c in row["incarnations"].values()]
    assert sorted(dropped)[0] == 0 and sorted(dropped)[1] == row["duplicate_dropped"], row
