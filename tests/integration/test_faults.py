"""Fault tolerance through real routers (issue 8): robots and the CEDDP killed and restarted, a
5-second link outage on an emulated WiFi link."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from arpz.netem import Impairments, NetemProxy, Outage
from tests.integration.fleet import Process, ceddp, settle, write_robot
from tests.support import free_port, free_udp_port, wait_until

pytestmark = pytest.mark.integration

#: KEEP_ALL + TRANSIENT_LOCAL: a reader that (re)joins gets the writer's whole history
DURABLE = (
    '[sensor_qos]\nreliability = "reliable"\nhistory = "keep_all"\n'
    'durability = "transient_local"\nmax_samples = 5000\n'
)


def test_a_restarted_robot_is_a_new_incarnation(tmp_path: Path) -> None:
    with ceddp(tmp_path) as (server, endpoint):
        config = write_robot(tmp_path, "robot1", endpoint, preset="machine2")
        first = Process("robot1", ["-m", "arpz.robot", "--config", str(config)], tmp_path)
        try:
            first.wait_for("running")
            settle(1.0)
            first.popen.send_signal(signal.SIGKILL)
            wait_until(
                lambda: "robot robot1 left" in server.output(),
                timeout_s=15,
                what="the CEDDP to see robot1 gone",
            )
        finally:
            first.kill()
        second = Process("robot1b", ["-m", "arpz.robot", "--config", str(config)], tmp_path)
        try:
            second.wait_for("running")
            wait_until(
                lambda: server.output().count("robot robot1 joined") == 2, what="robot1 back"
            )
            settle(1.0)
            assert second.interrupt() == 0
        finally:
            second.kill()
        assert server.interrupt() == 0, server.output()
    row = json.loads((tmp_path / "summary.json").read_text())["robots"]["robot1"]
    assert (row["joins"], row["leaves"]) == (2, 2)
    for topic, t in row["topics"].items():
        # the new incarnation's seq restarts at 1: a new writer, never taken for a huge gap
        assert t["lost"] == 0 and t["out_of_order"] == 0, (topic, t)
        if t["received"] > 0 and t["sent"] > 0:
            assert t["writer_changes"] == 1, (topic, t)


def test_the_ceddp_killed_and_restarted_loses_nothing_with_keep_all(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    rrd = tmp_path / "ceddp.rrd"
    config = tmp_path / "ceddp.toml"
    config.write_text(
        f'fleet = "itest"\nlisten = ["{endpoint}"]\nrrd = "{rrd.as_posix()}"\n'
        f'summary_json = "{(tmp_path / "summary.json").as_posix()}"\n{DURABLE}'
    )
    robot_config = write_robot(
        tmp_path, "robot1", endpoint, preset="machine2", rate_hz=20, extra=DURABLE
    )
    robot_config.write_text(
        robot_config.read_text().replace("[local_cache]\n", "[local_cache]\nenabled = false\n")
    )
    first = Process("ceddp1", ["-m", "arpz.ceddp", "--config", str(config)], tmp_path)
    robot = None
    try:
        first.wait_for("ready on")
        robot = Process("robot1", ["-m", "arpz.robot", "--config", str(robot_config)], tmp_path)
        robot.wait_for("running")
        settle(1.5)
        first.popen.send_signal(signal.SIGKILL)  # no goodbye, no footer in its .rrd
        first.popen.wait(10)
        settle(2.0)  # the robot goes on sensing with nobody listening
        second = Process("ceddp2", ["-m", "arpz.ceddp", "--config", str(config)], tmp_path)
        try:
            second.wait_for("ready on")
            wait_until(
                lambda: "robot robot1 joined" in second.output(),
                timeout_s=20,
                what="the robot to reconnect by itself",
            )
            settle(1.5)
            assert robot.interrupt() == 0, robot.output()
            assert second.interrupt() == 0, second.output()
        finally:
            second.kill()
    finally:
        first.kill()
        if robot is not None:
            robot.kill()
    row = json.loads((tmp_path / "summary.json").read_text())["robots"]["robot1"]
    assert row["final_stats"] and row["held_back"] == 0
    # everything the robot sent, before, during and after the outage, reached the new CEDDP
    assert row["sent"] == row["received"] > 100 and row["lost"] == 0, row
    # the first run's recording was kept, repaired, and verifies
    kept = [p for p in tmp_path.glob("ceddp.*.rrd")]
    assert len(kept) == 1, list(tmp_path.iterdir())
    for path in (kept[0], rrd):
        verify = subprocess.run(
            [sys.executable, "-m", "rerun", "rrd", "verify", str(path)],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert verify.returncode == 0, (path, verify.stdout + verify.stderr)


@pytest.mark.parametrize("max_samples", [5000, 40])
def test_a_5_s_link_outage(tmp_path: Path, max_samples: int) -> None:
    udp = f"udp/127.0.0.1:{free_udp_port()}"
    proxy_port = free_udp_port()
    qos = (
        '[sensor_qos]\nreliability = "reliable"\nhistory = "keep_all"\n'
        f"max_samples = {max_samples}\n"
    )
    proxy = NetemProxy(f"udp/127.0.0.1:{proxy_port}", udp, Impairments())
    with ceddp(tmp_path, extra=qos, also_listen=(udp,)) as (server, _endpoint):
        proxy.start()
        try:
            config = write_robot(
                tmp_path,
                "robot1",
                f"udp/127.0.0.1:{proxy_port}",
                preset="machine2",
                rate_hz=20,
                extra=qos,
            )
            config.write_text(
                config.read_text().replace("[local_cache]\n", "[local_cache]\nenabled = false\n")
            )
            robot = Process("robot1", ["-m", "arpz.robot", "--config", str(config)], tmp_path)
            try:
                robot.wait_for("running")
                settle(1.0)  # matched and flowing
                # the outage starts now, however long the robot took to start
                proxy.set_impairments(
                    Impairments(
                        clean_s=proxy.elapsed_s, outages=(Outage(start_s=0.0, duration_s=5.0),)
                    )
                )
                settle(8.0)  # 5 s down, 3 s to recover
                assert robot.interrupt(timeout_s=30) == 0, robot.output()
            finally:
                robot.kill()
            assert server.interrupt() == 0, server.output()
        finally:
            report = proxy.stop()
    assert report.up.dropped_outage > 0, report
    row = json.loads((tmp_path / "summary.json").read_text())["robots"]["robot1"]
    assert row["final_stats"]
    assert row["produced"] == row["sent"] + row["held_back"] + row["write_failures"]
    assert row["sent"] == row["received"] + row["lost"]
    if max_samples == 5000:
        # within KEEP_ALL's limits nothing is lost: the channel resends what the outage ate
        assert row["lost"] == 0 and row["write_failures"] == 0 and row["retransmitted"] > 0
    else:
        # beyond them, what could not be kept is refused at the writer and reported
        assert row["write_failures"] > 0 and row["lost"] == 0
