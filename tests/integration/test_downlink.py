"""Issue 14: nothing lost in either direction. The CEDDP -> robot path (Hello hops, the QoS
assignment, commands) and the robots' reports go through the reliable channel, over a real
router and an emulated lossy UDP link; a robot and a CEDDP that disagree on the mode report
INCOMPATIBLE_QOS on both sides."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from arpz.netem import Impairments, Outage
from tests.integration.fleet import Process, ceddp, robots, settle, udp_link, write_robot
from tests.support import client, wait_until

pytestmark = pytest.mark.integration

#: the Hello hops with KEEP_ALL: nothing the link loses may stay lost
HELLO_KEEP_ALL = '[hello_qos]\nreliability = "reliable"\nhistory = "keep_all"\n'
QOS_ON = "[qos]\nenabled = true\nrmax_hz = 100\n"


def summary(tmp: Path) -> dict:  # type: ignore[type-arg]
    return json.loads((tmp / "summary.json").read_text())  # type: ignore[no-any-return]


@pytest.mark.parametrize("loss", [0.1, 0.3])
def test_every_downlink_message_is_delivered_or_reported_lost(tmp_path: Path, loss: float) -> None:
    link = udp_link()
    udp, proxy = link.ceddp_endpoint, link.proxy
    with (
        ceddp(tmp_path, extra=QOS_ON + HELLO_KEEP_ALL, also_listen=(udp,)) as (server, endpoint),
        client(endpoint) as operator,
    ):
        proxy.start()
        try:
            config = write_robot(
                tmp_path,
                "robot1",
                link.robot_endpoint,
                preset="machine2",
                rate_hz=20,
                hello=True,
                extra=HELLO_KEEP_ALL,
            )
            with robots(tmp_path, [config]) as (robot,):
                wait_until(lambda: "QoS epoch 1 applied" in robot.output(), what="epoch 1")
                link.impair(Impairments(loss=loss))  # from now on: the session is up
                for _ in range(3):  # new assignments while the link loses, both ways
                    settle(1.0)  # deliberately: one a second, Hellos going round meanwhile
                    operator.put("arpz/itest/ceddp/qos/request", b"")

                def last_assignment_acknowledged() -> bool:
                    out = server.output()
                    requested = re.findall(r"QoS epoch (\d+) \(requested\)", out)
                    return len(requested) == 3 and (
                        f"robot robot1 applied QoS epoch {requested[-1]}:" in out
                    )

                wait_until(
                    last_assignment_acknowledged,
                    timeout_s=20,
                    what="the robot's acknowledgement of the last assignment at the CEDDP",
                )
                assert robot.interrupt(timeout_s=30) == 0, robot.output()
            assert server.interrupt() == 0, server.output()
        finally:
            report = proxy.stop()
    # the link really lost datagrams both ways
    assert report.up.dropped > 0 and report.down.dropped > 0, report
    row = summary(tmp_path)["robots"]["robot1"]
    assert row["final_stats"], row
    assert row["incompatible_qos"] == []
    hello_down = row["downlink"]["hello"]
    # every Hello hop the CEDDP wrote within the match is delivered or reported lost
    assert hello_down["reconciled"] is True, hello_down
    assert hello_down["written"] > 20 and hello_down["refused"] == 0, hello_down
    # KEEP_ALL on all four hops: not one Hello lost, though the link lost `loss` of datagrams
    hello = row["hello"]
    assert hello["sent"] > 20 and hello["lost"] == 0 and hello["late"] == 0, hello
    assert hello["sent"] == hello["received"], hello
    # the sensors' own reconciliation still holds through the lossy link
    assert row["sent"] == row["received"] + row["lost"], row
    # the assignment in force reached the robot: its last ack is for the CEDDP's last epoch
    qos = summary(tmp_path)["qos"]
    last_epoch = qos["assignments"][-1]["epoch"]
    assert qos["acks"]["robot1"]["epoch"] == last_epoch, qos


def test_an_assignment_made_during_an_outage_arrives_when_the_link_is_back(
    tmp_path: Path,
) -> None:
    """robot1 is cut off for 5 s; robot2 joins meanwhile, so the optimiser re-rates the fleet.
    The new assignment (TRANSIENT_LOCAL, KEEP_LAST 1) reaches robot1 once its link is back."""
    link = udp_link()
    udp, proxy = link.ceddp_endpoint, link.proxy
    with ceddp(tmp_path, extra=QOS_ON, also_listen=(udp,)) as (server, endpoint):
        proxy.start()
        try:
            cut = write_robot(
                tmp_path, "robot1", link.robot_endpoint, preset="machine2", rate_hz=20
            )
            with robots(tmp_path, [cut]) as (robot1,):
                wait_until(lambda: "QoS epoch 1 applied" in robot1.output(), what="the first epoch")
                outage = Outage(start_s=0.0, duration_s=5.0)
                proxy.set_impairments(
                    Impairments(clean_s=proxy.elapsed_s, outages=(outage,)),
                    Impairments(clean_s=proxy.elapsed_s, outages=(outage,)),
                )
                second = write_robot(tmp_path, "robot2", endpoint, preset="machine1", rate_hz=20)
                robot2 = Process("robot2", ["-m", "arpz.robot", "--config", str(second)], tmp_path)
                try:
                    robot2.wait_for("running")
                    wait_until(
                        lambda: (
                            "robot robot2 uses" in server.output()
                            or "robot2 joined with" in server.output()
                        ),
                        what="the CEDDP to re-solve for robot2",
                    )
                    epochs_during_outage = server.output().count("QoS epoch")
                    assert "QoS epoch 2 applied" not in robot1.output()  # still cut off
                    wait_until(
                        lambda: (
                            "QoS epoch 2 applied" in robot1.output()
                            or "QoS epoch 3 applied" in robot1.output()
                        ),
                        timeout_s=20,
                        what="robot1 to receive the assignment made during its outage",
                    )
                    assert robot2.interrupt() == 0, robot2.output()
                finally:
                    robot2.kill()
                assert robot1.interrupt(timeout_s=30) == 0, robot1.output()
            assert server.interrupt() == 0, server.output()
        finally:
            report = proxy.stop()
    assert report.down.dropped_outage > 0, report
    assert epochs_during_outage >= 2
    qos = summary(tmp_path)["qos"]
    # both robots ended on the epoch in force when they stopped
    assert qos["acks"]["robot1"]["status"] == "applied", qos


def test_a_restarted_ceddp_sends_its_assignment(tmp_path: Path) -> None:
    with ceddp(tmp_path, extra=QOS_ON) as (first, endpoint):
        config = write_robot(tmp_path, "robot1", endpoint, preset="machine2", rate_hz=20)
        robot = Process("robot1", ["-m", "arpz.robot", "--config", str(config)], tmp_path)
        try:
            robot.wait_for("running")
            wait_until(lambda: "QoS epoch 1 applied" in robot.output(), what="epoch 1")
            first.kill()  # SIGKILL: no goodbye
            applied_before = robot.output().count("QoS epoch 1 applied")
            config_path = tmp_path / "ceddp.toml"
            second = Process("ceddp2", ["-m", "arpz.ceddp", "--config", str(config_path)], tmp_path)
            try:
                second.wait_for("ready on")
                wait_until(
                    lambda: robot.output().count("QoS epoch 1 applied") > applied_before,
                    timeout_s=30,
                    what="the restarted CEDDP's first assignment to reach the robot",
                )
                wait_until(
                    lambda: "robot robot1 applied QoS epoch" in second.output(),
                    timeout_s=10,
                    what="the robot's acknowledgement at the new CEDDP",
                )
                assert robot.interrupt() == 0, robot.output()
                assert second.interrupt() == 0, second.output()
            finally:
                second.kill()
        finally:
            robot.kill()
    qos = summary(tmp_path)["qos"]
    assert qos["acks"]["robot1"]["status"] == "applied", qos


def test_a_plain_robot_and_a_channel_ceddp_are_incompatible_on_both_sides(
    tmp_path: Path,
) -> None:
    """The new user's mistake: ``reliability = "none"`` on one side only. Nothing is lost
    silently: both report INCOMPATIBLE_QOS, the robot's samples are counted as refused, and the
    robot stays out of the QoS optimiser."""

    def both_robots_counted() -> bool:
        """The CEDDP's periodic summary: robot1's samples received, robot2's refused."""
        try:
            robots_now = summary(tmp_path)["robots"]
        except FileNotFoundError:
            return False
        return (
            robots_now.get("robot1", {}).get("received", 0) > 0
            and robots_now.get("robot2", {}).get("refused", 0) > 0
        )

    with ceddp(tmp_path, extra="summary_period_s = 0.2\n" + QOS_ON) as (server, endpoint):
        good = write_robot(tmp_path, "robot1", endpoint, preset="machine2", rate_hz=20)
        plain = write_robot(
            tmp_path,
            "robot2",
            endpoint,
            preset="machine1",
            rate_hz=20,
            top='reliability = "none"\nmatch_timeout_s = 1\n',
        )
        with robots(tmp_path, [good, plain]) as (robot1, robot2):
            wait_until(
                lambda: "INCOMPATIBLE_QOS" in robot2.output(),
                what="the plain robot to report INCOMPATIBLE_QOS",
            )
            wait_until(
                lambda: "robot robot2: INCOMPATIBLE_QOS" in server.output(),
                what="the CEDDP to report robot2 INCOMPATIBLE_QOS",
            )
            wait_until(both_robots_counted, what="robot1's samples received, robot2's refused")
            assert robot2.interrupt() == 0, robot2.output()
            assert robot1.interrupt() == 0, robot1.output()
        assert server.interrupt() == 0, server.output()
    result = summary(tmp_path)
    bad = result["robots"]["robot2"]
    assert bad["incompatible_qos"], bad
    assert bad["refused"] > 0, bad
    assert bad["received"] == 0
    good_row = result["robots"]["robot1"]
    assert good_row["incompatible_qos"] == [] and good_row["received"] > 0
    # the optimiser never counted robot2's topics
    for assignment in result["qos"]["assignments"]:
        assert "robot2" not in assignment["robots"], assignment


def _mission_robot(tmp: Path, robot: str, endpoint: str) -> Path:
    path = tmp / f"{robot}.toml"
    path.write_text(
        f'robot_id = "{robot}"\nfleet = "itest"\nconnect = ["{endpoint}"]\nseed = {robot[-1]}\n'
        "stats_period_s = 0.2\nconnect_timeout_s = 30\n"
        '[sim]\nworld = "hallway_small"\nbeam_rate_hz = 20\n'
    )
    return path


def _log_time(line: str) -> float:
    """The wall-clock time of an arpz log line ("2026-12-01 21:14:09,622 LEVEL ...")."""
    import datetime as dt

    stamp = dt.datetime.strptime(line[:23], "%Y-%m-%d %H:%M:%S,%f")
    return stamp.timestamp()


@pytest.mark.slow
def test_killing_the_ceddp_stops_every_robot_within_its_command_deadline(tmp_path: Path) -> None:
    """The hallway mission: the CEDDP dies (SIGKILL), so velocity commands stop; each robot's
    watchdog brings its body to a safe stop within the 0.5 s deadline (plus its check period),
    and a restarted CEDDP's commands make every robot move again."""
    import time

    mission = '[mission]\nworld = "hallway_small"\ntime_limit_s = 120\n'
    with ceddp(tmp_path, extra=mission) as (first, endpoint):
        configs = [_mission_robot(tmp_path, f"robot{i}", endpoint) for i in (1, 2, 3)]
        with robots(tmp_path, configs) as procs:
            wait_until(
                lambda: "mission: all 3 robots present" in first.output(),
                timeout_s=30,
                what="the mission to start",
            )
            settle(3.0)  # deliberately: the robots drive for a while before the CEDDP dies
            killed_at = time.time()
            first.kill()
            wait_until(
                lambda: all("safe stop" in p.output() for p in procs),
                timeout_s=10,
                what="every robot's watchdog to stop it",
            )
            for proc in procs:
                line = next(x for x in proc.lines if "safe stop" in x)
                # deadline 0.5 s, checked every 0.05 s; a loaded 2-core host adds a little
                assert _log_time(line) - killed_at < 0.5 + 0.05 + 0.35, (proc.name, line)
            config_path = tmp_path / "ceddp.toml"
            second = Process("ceddp2", ["-m", "arpz.ceddp", "--config", str(config_path)], tmp_path)
            try:
                second.wait_for("ready on")
                wait_until(
                    lambda: all("resuming" in p.output() for p in procs),
                    timeout_s=30,
                    what="every robot to resume on the new CEDDP's commands",
                )
                settle(1.0)  # deliberately: a second of driving on the new CEDDP's commands
                for proc in procs:
                    assert proc.interrupt() == 0, proc.output()
                assert second.interrupt() == 0, second.output()
            finally:
                second.kill()
    row = summary(tmp_path)["robots"]
    for robot in ("robot1", "robot2", "robot3"):
        assert row[robot]["watchdog_stops"].get("velocity", 0) >= 1, row[robot]
        down = row[robot]["downlink"]["velocity"]
        assert down["written"] > 0 and down["reconciled"] is True, down


# timing-bound: beside the experiment's fleet on two shared cores its recoveries measured 141 and
# 221 ms in two full runs, while alone or beside two CPU hogs 43-85 ms; so it runs with the cores
# to itself (tests/conftest.py, cpu_share)
@pytest.mark.cpu_exclusive
def test_a_lost_change_does_not_leave_the_ceddp_on_a_stale_value(tmp_path: Path) -> None:
    """The local cache with KEEP_LAST 1 at 1 kHz over wifi-bad: a value that changes every 100 ms
    (99 of 100 readings held back as unchanged). A change the link loses must not leave the CEDDP
    on the old value until the next change or heartbeat: the repeats held back announce it (a
    heartbeat at every held-back reading while it is unacknowledged, at most one per NACK
    delay), so it is NACKed and resent within a round trip or a few. Each recovery round takes
    one and a half round trips and the NACK delay; a round whose NACK or resend is lost too adds
    the NACK period (20 ms).

    The writers' heartbeat period is 500 ms here, five changes: a change recovered only by a
    heartbeat is overwritten by the next change first (KEEP_LAST 1), reported lost. With the
    period at 100 ms that effect was too small to see in ~10 losses a run: with the announcing
    heartbeats turned off the worst change still arrived within 73-121 ms (4 runs) against
    33-52 ms with them, 100.3 and 102.8 ms on a slowed CI host."""
    from arpz.experiment.runner import impairments
    from arpz.experiment.spec import PROFILES

    trace = tmp_path / "steps.csv"
    trace.write_text(
        "t_s,value\n" + "".join(f"{i * 0.1:.1f},{10.0 if i % 2 else 20.0}\n" for i in range(100))
    )
    qos = (
        '[sensor_qos]\nreliability = "reliable"\nhistory = "keep_last"\ndepth = 1\n'
        "heartbeat_period_s = 0.5\n"
    )
    sensor = (
        '[[sensors]]\nname = "step"\nkind = "ultrasonic"\nrate_hz = 1000\ndriver = "replay"\n'
        f'trace = "{trace.as_posix()}"\noptions = {{ loop = true }}\n'
    )
    link = udp_link()
    udp, proxy = link.ceddp_endpoint, link.proxy
    with ceddp(tmp_path, extra=qos, also_listen=(udp,)) as (server, _):
        proxy.start()
        try:
            config = write_robot(
                tmp_path,
                "robot1",
                link.robot_endpoint,
                preset="machine2",
                rate_hz=10,
                extra=qos + sensor,
            )
            with robots(tmp_path, [config]) as (robot,):
                wait_until(lambda: "robot robot1 joined" in server.output(), what="robot1")
                link.impair(impairments(PROFILES["wifi-bad"]))
                settle(12.0)  # deliberately: 12 s over wifi-bad, about 120 changes to lose
                assert robot.interrupt(timeout_s=30) == 0, robot.output()
            assert server.interrupt() == 0, server.output()
        finally:
            report = proxy.stop()
    assert report.up.dropped > 0 and report.down.dropped > 0, report
    step = summary(tmp_path)["robots"]["robot1"]["topics"]["step"]
    assert step["held_back"] > 10 * step["sent"] > 0, step  # the cache did hold repeats back
    assert step["received"] > 100, step
    # some changes were lost on the link and recovered (wifi-bad loses about 8 % of datagrams)
    assert step["retransmitted"] > 0, step
    # none waited for a heartbeat: not one overwritten by the next change (one allowed for a
    # slowed host's 4-5 lost rounds in a row; with the announcing heartbeats off, 4 runs lost
    # 1-4 at a 100 ms period, more at 500), and none took a change period to arrive
    change_period_ms = 100.0
    assert step["lost"] <= 1, step
    assert step["received"] + step["lost"] == step["sent"], step
    assert step["staleness_ms_p99"] < 0.75 * change_period_ms, step
    assert step["staleness_ms_max"] < 1.5 * change_period_ms, step
