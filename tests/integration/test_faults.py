"""Fault tolerance through real routers (issue 8): robots and the CEDDP killed and restarted, a
5-second link outage on an emulated WiFi link."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from arpz.netem import Impairments, NetemProxy, Outage
from tests.integration.fleet import Process, ceddp, settle, udp_link, write_robot
from tests.support import free_port, free_udp_port, wait_until

# heavy or timing-bound: runs with the cores to itself (tests/conftest.py, cpu_share)
pytestmark = [pytest.mark.integration, pytest.mark.cpu_exclusive]

#: KEEP_ALL + TRANSIENT_LOCAL: a reader that (re)joins gets the writer's whole history
DURABLE = (
    '[sensor_qos]\nreliability = "reliable"\nhistory = "keep_all"\n'
    'durability = "transient_local"\nmax_samples = 5000\n'
)
#: how often the CEDDPs below write their summary while running: the waits poll it
SUMMARY_EVERY = "summary_period_s = 0.2\n"


def _robot_row(summary_json: Path, robot: str = "robot1") -> dict[str, Any] | None:
    """The robot's row in the CEDDP's latest summary (written atomically); None before one."""
    try:
        summary = json.loads(summary_json.read_text())
    except FileNotFoundError:
        return None
    row: dict[str, Any] | None = summary["robots"].get(robot)
    return row


def _sensor_topics(row: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return {name: t for name, t in row["topics"].items() if name != "hello"}


def test_a_restarted_robot_is_a_new_incarnation(tmp_path: Path) -> None:
    summary_json = tmp_path / "summary.json"

    def incarnations_received() -> list[int]:
        """What the CEDDP received from each incarnation it has a report of, oldest first."""
        row = _robot_row(summary_json)
        return [] if row is None else [i["received"] for i in row["incarnations"].values()]

    with ceddp(tmp_path, extra=SUMMARY_EVERY) as (server, endpoint):
        config = write_robot(tmp_path, "robot1", endpoint, preset="machine2")
        first = Process("robot1", ["-m", "arpz.robot", "--config", str(config)], tmp_path)
        try:
            first.wait_for("running")
            wait_until(
                lambda: [n > 0 for n in incarnations_received()] == [True],
                what="a report of robot1's first incarnation and its samples at the CEDDP",
            )
            first.popen.send_signal(signal.SIGKILL)
            wait_until(
                lambda: "robot robot1 unreachable" in server.output(),
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
            wait_until(
                lambda: [n > 0 for n in incarnations_received()] == [True, True],
                what="a report of robot1's second incarnation and its samples at the CEDDP",
            )
            assert second.interrupt() == 0
        finally:
            second.kill()
        assert server.interrupt() == 0, server.output()
    row = json.loads((tmp_path / "summary.json").read_text())["robots"]["robot1"]
    assert (row["joins"], row["leaves"]) == (2, 2)
    for topic, t in row["topics"].items():
        assert t["lost"] == 0 and t["out_of_order"] == 0, (topic, t)
    # the new incarnation's seq restarts at 1: a new writer, never taken for a huge gap; checked
    # on every topic both incarnations sent on (there must be some, or nothing was checked)
    both = {topic: t for topic, t in row["topics"].items() if t["received"] > 0 and t["sent"] > 0}
    assert both, row["topics"]
    for topic, t in both.items():
        assert t["writer_changes"] == 1, (topic, t)
    # each incarnation reported on its own: the killed one without a final report, the second
    # reconciled exactly (its sent == its received + lost), neither merged into the other
    incarnations = list(row["incarnations"].values())
    assert len(incarnations) == 2, row["incarnations"]
    killed, restarted = incarnations
    assert not killed["final"] and killed["reconciled"] is None and killed["received"] > 0
    assert restarted["final"] and restarted["reconciled"], restarted
    assert restarted["sent"] == restarted["received"] > 0 and restarted["lost"] == 0
    sensors = [t for name, t in row["topics"].items() if name != "hello"]
    assert sum(t["received"] for t in sensors) == killed["received"] + restarted["received"]


def _durable_pair(
    tmp: Path, endpoint: str, rate_hz: int, ceddp_extra: str = ""
) -> tuple[Path, Path]:
    """A CEDDP and a machine2 robot config with the no-loss profile and the local cache off."""
    config = tmp / "ceddp.toml"
    config.write_text(
        f'fleet = "itest"\nlisten = ["{endpoint}"]\nrrd = "{(tmp / "ceddp.rrd").as_posix()}"\n'
        f'summary_json = "{(tmp / "summary.json").as_posix()}"\n{ceddp_extra}{DURABLE}'
    )
    robot_config = write_robot(
        tmp, "robot1", endpoint, preset="machine2", rate_hz=rate_hz, extra=DURABLE
    )
    robot_config.write_text(
        robot_config.read_text().replace("[local_cache]\n", "[local_cache]\nenabled = false\n")
    )
    return config, robot_config


def test_the_ceddp_killed_and_restarted_loses_nothing_with_keep_all(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    rrd = tmp_path / "ceddp.rrd"
    summary_json = tmp_path / "summary.json"
    config, robot_config = _durable_pair(
        tmp_path, endpoint, 20, 'summary_period_s = 0.5\nprevious_summary = "latest"\n'
    )

    def caught_up() -> bool:
        """The second CEDDP's summary: the catch-up brought the first run's samples again (each
        topic has repeats) and everything the robot reported sent has arrived."""
        row = _robot_row(summary_json)
        return (
            row is not None
            and all(t["repeated_from_previous_run"] > 0 for t in _sensor_topics(row).values())
            and row["received"] >= row["sent"] > 0
        )

    first = Process("ceddp1", ["-m", "arpz.ceddp", "--config", str(config)], tmp_path)
    robot = None
    try:
        first.wait_for("ready on")
        robot = Process("robot1", ["-m", "arpz.robot", "--config", str(robot_config)], tmp_path)
        robot.wait_for("running")
        wait_until(
            lambda: (
                (row := _robot_row(summary_json)) is not None
                and bool(_sensor_topics(row))
                and all(t["received"] > 0 for t in _sensor_topics(row).values())
            ),
            what="a persisted summary with samples of every robot1 topic",
        )
        first.popen.send_signal(signal.SIGKILL)  # no goodbye, no footer in its .rrd
        first.popen.wait(10)
        # ... but a summary at most summary_period_s old to reconcile against
        persisted = json.loads((tmp_path / "summary.json").read_text())
        assert persisted["complete"] is False and persisted["robots"]["robot1"]["received"] > 0
        # deliberately 2 s of the robot sensing with nobody listening: what the restart recovers
        settle(2.0)
        _restart_and_catch_up(tmp_path, config, robot, caught_up, catch_up_s=20)
    finally:
        first.kill()
        if robot is not None:
            robot.kill()
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["complete"] is True
    row = summary["robots"]["robot1"]
    assert row["final_stats"] and row["held_back"] == 0
    # the first run's samples came again in the restart's catch-up: flagged, and the two runs
    # reconcile (what the first received + what only the second did == what the robot sent)
    first_topics = persisted["robots"]["robot1"]["topics"]
    topics = _sensor_topics(row)
    assert topics and set(topics) <= set(first_topics), (sorted(topics), sorted(first_topics))
    for topic, t in topics.items():
        repeated = t["repeated_from_previous_run"]
        assert 0 < repeated <= first_topics[topic]["received"], (topic, t)
        assert first_topics[topic]["received"] + t["received"] - repeated <= t["sent"], (topic, t)
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
    summary_json = tmp_path / "summary.json"
    with ceddp(tmp_path, extra=SUMMARY_EVERY + qos, also_listen=(udp,)) as (server, _endpoint):
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
                wait_until(
                    lambda: (row := _robot_row(summary_json)) is not None and row["received"] > 0,
                    what="robot1's samples flowing to the CEDDP",
                )
                flowing = _robot_row(summary_json)
                assert flowing is not None
                sent_before = flowing["sent"]
                # the outage starts now, however long the robot took to start
                proxy.set_impairments(
                    Impairments(
                        clean_s=proxy.elapsed_s, outages=(Outage(start_s=0.0, duration_s=5.0),)
                    )
                )
                settle(5.0)  # deliberately: the outage itself, with the robot sensing on
                wait_until(
                    lambda: (
                        (row := _robot_row(summary_json)) is not None
                        and row["received"] + row["lost"] >= row["sent"] > sent_before
                    ),
                    timeout_s=20,
                    what="a report from after the outage and every sample it counts accounted for",
                )
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


@pytest.mark.parametrize("rate_hz", [200, 400])
def test_the_ceddp_killed_at_high_rate_declares_nothing_lost_that_the_robot_held(
    tmp_path: Path, rate_hz: int
) -> None:
    """Issue 15, item 4: kill -9 of the CEDDP at 200 and 400 Hz per topic with the no-loss
    profile (KEEP_ALL + TRANSIENT_LOCAL, 5 000 samples). The whole run fits in the robot's
    history, so the restarted CEDDP must receive every sample and declare none lost (before:
    1 318 declared lost), and the robot resends its history about once to the new reader
    (before the resend echo and the answer-time hold: 15 315 resends for 2 296 samples per topic
    at 200 Hz, 15 359 for 4 383 at 400 Hz; measured since, 1.00-1.19 times what it held)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    summary_json = tmp_path / "summary.json"
    config, robot_config = _durable_pair(tmp_path, endpoint, rate_hz, "summary_period_s = 0.5\n")

    def caught_up() -> bool:
        """The second CEDDP's summary: everything the robot reported sent has arrived."""
        row = _robot_row(summary_json)
        return row is not None and row["received"] >= row["sent"] > 0

    first = Process("ceddp1", ["-m", "arpz.ceddp", "--config", str(config)], tmp_path)
    robot = None
    try:
        first.wait_for("ready on")
        robot = Process("robot1", ["-m", "arpz.robot", "--config", str(robot_config)], tmp_path)
        robot.wait_for("running")
        settle(2.0)  # deliberately: 2 s at full rate fill the history the restart must resend
        first.popen.send_signal(signal.SIGKILL)
        first.popen.wait(10)
        # the first run's periodic summary must not be taken for the second's
        summary_json.unlink(missing_ok=True)
        settle(2.0)  # deliberately: 2 s with no CEDDP, the robot writing on
        _restart_and_catch_up(tmp_path, config, robot, caught_up, catch_up_s=30)
    finally:
        first.kill()
        if robot is not None:
            robot.kill()
    row = json.loads((tmp_path / "summary.json").read_text())["robots"]["robot1"]
    assert row["final_stats"], row
    assert _sensor_topics(row), row
    for topic, t in _sensor_topics(row).items():
        assert t["sent"] < 5000, (topic, t)  # the run fits in the history: nothing may be lost
        assert t["received"] == t["sent"] and t["lost"] == 0, (topic, t)
        held = t["history_offered"]  # what the history held when each reader matched
        print(f"{rate_hz} Hz {topic}: {t['retransmitted']} resends of a {held}-sample history")
        assert held > 0.3 * t["sent"], (topic, t)  # the outage's samples were in it
        # about once per reader: measured 1.00 for most topics, at worst 1.19 (one answer of 256
        # resends sent twice); 1.5 leaves room for a loaded host, 6.6 (before) fails
        assert t["retransmitted"] <= 1.5 * held, (topic, t)


def _restart_and_catch_up(
    tmp_path: Path,
    config: Path,
    robot: Process,
    caught_up: Callable[[], bool],
    *,
    catch_up_s: float,
) -> None:
    """A second CEDDP on the killed one's config: the robot reconnects by itself and the
    restarted CEDDP catches up on what it missed; then both stop cleanly."""
    second = Process("ceddp2", ["-m", "arpz.ceddp", "--config", str(config)], tmp_path)
    try:
        second.wait_for("ready on")
        wait_until(
            lambda: "robot robot1 joined" in second.output(),
            timeout_s=20,
            what="the robot to reconnect by itself",
        )
        wait_until(caught_up, timeout_s=catch_up_s, what="the restarted CEDDP to catch up")
        assert robot.interrupt(timeout_s=30) == 0, robot.output()
        assert second.interrupt() == 0, second.output()
    finally:
        second.kill()


def test_a_dead_zone_longer_than_the_lease_is_one_outage_and_nothing_arrives_twice(
    tmp_path: Path,
) -> None:
    """Issue 39: a 12 s dead zone (Zenoh's lease is 10 s) ended the robot's session; when it
    was back its KEEP_ALL TRANSIENT_LOCAL writers' history was taken again as new (sent 14 331,
    received 17 218, ``reconciled: false``) and about 200 Hello commands were counted nowhere.
    The robot comes back as the same incarnation: one outage with its duration, every sample
    of every topic received once or reported lost, and the downlink reconciled."""
    link = udp_link()
    summary_json = tmp_path / "summary.json"
    with ceddp(tmp_path, extra=SUMMARY_EVERY + DURABLE, also_listen=(link.ceddp_endpoint,)) as (
        server,
        _endpoint,
    ):
        link.proxy.start()
        try:
            config = write_robot(
                tmp_path,
                "robot1",
                link.robot_endpoint,
                preset="machine2",
                rate_hz=20,
                hello=True,
                extra=DURABLE,
            )
            robot = Process("robot1", ["-m", "arpz.robot", "--config", str(config)], tmp_path)
            try:
                robot.wait_for("running")
                wait_until(
                    lambda: (row := _robot_row(summary_json)) is not None and row["sent"] > 0,
                    what="robot1's samples and reports flowing to the CEDDP",
                )
                link.impair(Impairments(outages=(Outage(start_s=0.0, duration_s=12.0),)))
                settle(12.0)  # deliberately: the dead zone itself, with the robot sensing on
                wait_until(
                    lambda: (
                        (row := _robot_row(summary_json)) is not None and len(row["outages_s"]) == 1
                    ),
                    timeout_s=60,
                    what="robot1 back after the dead zone",
                )
                settle(2.0)  # a little traffic after it
                assert robot.interrupt(timeout_s=30) == 0, robot.output()
            finally:
                robot.kill()
            assert server.interrupt() == 0, server.output()
        finally:
            report = link.proxy.stop()
    assert report.up.dropped_outage > 0, report
    summary = json.loads(summary_json.read_text())
    row = summary["robots"]["robot1"]
    assert row["final_stats"] and len(row["incarnations"]) == 1, row["incarnations"]
    # the dead zone, then the robot's own stop
    assert row["leaves"] == 2 and row["joins"] == 2, summary["events"]
    # the CEDDP sees the robot go when the router's lease (10 s) ends, and back as soon as
    # the link is: the robot reopens its session itself (docs/operations.md)
    assert 0.0 < row["outages_s"][0] <= 8.0, row["outages_s"]
    for name, topic in _sensor_topics(row).items():
        assert topic["sent"] == topic["received"] + topic["lost"], (name, topic)
    assert row["sent"] == row["received"] + row["lost"], row
    hello = row["downlink"]["hello"]
    assert hello["written"] > 0 and hello["reconciled"] is True, hello
    assert hello["written"] == (
        hello["unmatched"]
        + hello["write_failures"]
        + hello["before_match"]
        + hello["this_writer"]["delivered"]
        + hello["this_writer"]["lost"]
        + hello["this_writer"]["lifespan_expired"]
        + hello["after_robot_stopped"]
    ), hello
    events = [e for e in summary["events"] if "robot1" in e]
    assert any("back after" in e and "same incarnation" in e for e in events), events
    assert "robot robot1 left (it stopped" in events[-1], events
