"""The example lab of examples/lab (a team's own drivers, message type, planner and actuator,
docs/nodes.md) as real processes through a real router: typed readings reach the planner, its
command reaches the actuator, and every typed sample is reconciled; then what goes wrong with
types is refused clearly (an unknown type, a bad .msg, a driver's wrong message, a CEDDP that
does not know the robots' own type)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.integration.fleet import Process
from tests.support import free_port, wait_until

pytestmark = pytest.mark.integration
EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "lab"


def lab_copy(tmp_path: Path, *, robot_extra: str = "", ceddp_msg_paths: bool = True) -> str:
    shutil.copytree(EXAMPLE, tmp_path, dirs_exist_ok=True)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    for name in ("robot.toml", "ceddp.toml"):
        path = tmp_path / name
        text = path.read_text().replace("tcp/127.0.0.1:7447", endpoint)
        if name == "ceddp.toml":
            text = text.replace(
                'msg_paths = ["msg"]',
                ('msg_paths = ["msg"]' if ceddp_msg_paths else "")
                + '\nsummary_json = "summary.json"\nrrd = "ceddp.rrd"\nmetrics_period_s = 0.2',
            )
        else:
            text = text.replace('robot_id = "robot1"', 'robot_id = "robot1"\nstats_period_s = 0.2')
            text = text.replace("[actuator]", robot_extra + "\n[actuator]")
        path.write_text(text)
    return endpoint


def test_the_example_lab_docks_its_robot_and_reconciles_every_typed_sample(
    tmp_path: Path,
) -> None:
    lab_copy(tmp_path)
    ceddp = Process("ceddp", ["-m", "arpz.ceddp", "--config", "ceddp.toml"], tmp_path)
    try:
        ceddp.wait_for("ready on")
        robot = Process("robot1", ["-m", "arpz.robot", "--config", "robot.toml"], tmp_path)
        try:
            robot.wait_for("running")
            robot.wait_for("driving at 0.50 m/s", timeout_s=30)  # a Twist on cmd_vel
            robot.wait_for("driving at 0.20 m/s", timeout_s=60)  # slower as the battery drains
            ceddp.wait_for("sent to its dock", timeout_s=60)
            robot.wait_for("docked", timeout_s=30)
            ceddp.wait_for("robot1: dock service says True: docking at dock-1", timeout_s=30)
            ceddp.wait_for("robot1: docked at dock-1", timeout_s=30)
            # docked, it gets no cmd_vel: the watchdog stops it
            robot.wait_for("no cmd_vel command within its deadline: safe stop", timeout_s=30)
            assert robot.interrupt() == 0
        finally:
            robot.kill()
        assert ceddp.interrupt() == 0
    finally:
        ceddp.kill()
    summary = json.loads((tmp_path / "summary.json").read_text())
    robot1 = summary["robots"]["robot1"]
    for topic in ("gps", "battery", "dock_state"):
        row = robot1["topics"][topic]
        assert row["received"] == row["sent"] > 0, (topic, row)
        assert row["lost"] == 0 and row["driver_errors"] == 0, (topic, row)
    assert robot1["decode_errors"] == 0
    dock = summary["services"]["robot1"]["dock"]
    assert dock["caller"]["ok"] == dock["robot"]["ok"] == 1, dock
    cmd_vel = robot1["downlink"]["cmd_vel"]
    assert cmd_vel["delivered"] == cmd_vel["written"] > 0 and cmd_vel["reconciled"], cmd_vel
    assert robot1["watchdog_stops"].get("cmd_vel", 0) >= 1
    assert summary["planners"]["DockPlanner"]["errors"] == 0


def test_a_ceddp_without_the_robots_msg_paths_refuses_their_type_loudly(
    tmp_path: Path,
) -> None:
    lab_copy(tmp_path, ceddp_msg_paths=False)
    ceddp = Process("ceddp", ["-m", "arpz.ceddp", "--config", "ceddp.toml"], tmp_path)
    try:
        ceddp.wait_for("ready on")
        robot = Process("robot1", ["-m", "arpz.robot", "--config", "robot.toml"], tmp_path)
        try:
            robot.wait_for("running")
            ceddp.wait_for("type mylab/msg/DockState is unknown to this CEDDP", timeout_s=30)
            ceddp.wait_for("sent to its dock", timeout_s=60)  # the standard types still flow
            assert robot.interrupt() == 0
        finally:
            robot.kill()
        assert ceddp.interrupt() == 0
    finally:
        ceddp.kill()
    summary = json.loads((tmp_path / "summary.json").read_text())
    dock_state = summary["robots"]["robot1"]["topics"]["dock_state"]
    assert dock_state["received"] == 0 and dock_state["decode_errors"] > 0, dock_state
    assert any("unknown to this CEDDP" in event for event in summary["events"])


@pytest.mark.parametrize(
    ("change", "says"),
    [
        (
            lambda text: text.replace("sensor_msgs/msg/NavSatFix", "sensor_msgs/msg/NavSatFx"),
            "did you mean sensor_msgs/msg/NavSatFix",
        ),
        (
            lambda text: text.replace('type = "sensor_msgs/msg/NavSatFix"', 'type = "gps"'),
            "type must be a ROS 2 message type package/msg/Name",
        ),
    ],
)
def test_a_wrong_type_stops_the_robot_before_it_connects(
    tmp_path: Path, change: object, says: str
) -> None:
    lab_copy(tmp_path)
    config = tmp_path / "robot.toml"
    config.write_text(change(config.read_text()))  # type: ignore[operator]
    done = subprocess.run(
        [sys.executable, "-m", "arpz.robot", "--config", "robot.toml"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2, done.stderr
    assert says in done.stderr, done.stderr


def test_a_bad_msg_file_stops_the_robot_naming_the_file(tmp_path: Path) -> None:
    lab_copy(tmp_path)
    (tmp_path / "msg" / "mylab" / "msg" / "DockState.msg").write_text("bool docked\nflot32 d\n")
    done = subprocess.run(
        [sys.executable, "-m", "arpz.robot", "--config", "robot.toml"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2, done.stderr
    assert "DockState.msg" in done.stderr and "flot32" in done.stderr, done.stderr


def test_a_ros2_node_receives_the_labs_typed_topics_through_the_bridge(tmp_path: Path) -> None:
    """The CEDDP's bridge publishes each typed topic as CDR of its own type with ROS 2's type
    hash, the lab's own type too: a stand-in rmw_zenoh node (tests/integration/ros2_peer.py,
    rosbags' Jazzy definitions plus the lab's .msg) decodes every field; and its Twist on
    /robot1/cmd_vel reaches the lab's actuator as the message itself (a typed command)."""
    from rosbags.typesys import get_types_from_msg

    from tests.integration.ros2_peer import STORE, Ros2Peer

    endpoint = lab_copy(tmp_path)
    with (tmp_path / "ceddp.toml").open("a") as toml:
        toml.write(
            "\n[ros2]\nenabled = true\ndomain_id = 57\n[[ros2.commands]]\n"
            'topic = "/{robot}/cmd_vel"\ntype = "geometry_msgs/msg/Twist"\ncommand = "cmd_vel"\n'
        )
    dock_msg = (tmp_path / "msg" / "mylab" / "msg" / "DockState.msg").read_text()
    if "mylab/msg/DockState" not in STORE.fielddefs:
        STORE.register(get_types_from_msg(dock_msg, "mylab/msg/DockState"))
    ceddp = Process("ceddp", ["-m", "arpz.ceddp", "--config", "ceddp.toml"], tmp_path)
    try:
        ceddp.wait_for("ready on")
        robot = Process("robot1", ["-m", "arpz.robot", "--config", "robot.toml"], tmp_path)
        try:
            robot.wait_for("running")
            with Ros2Peer(endpoint, domain=57) as peer:
                topics = ("/robot1/gps", "/robot1/battery", "/robot1/dock_state")
                wait_until(
                    lambda: all(peer.find("MP", t) for t in topics),
                    timeout_s=20,
                    what="the typed topics' publisher tokens",
                )
                for topic in topics:
                    entity = peer.find("MP", topic)
                    assert entity is not None
                    assert entity.type_hash == STORE.hash_rihs01(entity.ros_type), topic
                    peer.subscribe(entity)
                wait_until(
                    lambda: all(len(peer.messages(t)) >= 2 for t in topics),
                    timeout_s=20,
                    what="two messages of each typed topic",
                )
                fix = peer.messages("/robot1/gps")[-1].message
                assert fix.latitude == pytest.approx(51.4545, abs=1e-3)
                assert fix.header.frame_id == "gps"
                battery = peer.messages("/robot1/battery")[-1].message
                assert 0.0 <= battery.percentage <= 1.0 and battery.serial_number == "lab-0001"
                dock = peer.messages("/robot1/dock_state")[-1].message
                assert dock.distance_m in (0.0, 2.5) and isinstance(dock.docked, bool)
                wait_until(lambda: peer.find("MS", "/robot1/cmd_vel") is not None, timeout_s=20)
                key = peer.publisher("/robot1/cmd_vel", "geometry_msgs/msg/Twist")
                for _ in range(50):
                    peer.publish(key, "geometry_msgs/msg/Twist", peer.twist(0.3, 0.0))
                    if robot.has_line("driving at 0.30 m/s"):
                        break
                    time.sleep(0.1)
                robot.wait_for("driving at 0.30 m/s", timeout_s=10)
            assert robot.interrupt() == 0
        finally:
            robot.kill()
        assert ceddp.interrupt() == 0
    finally:
        ceddp.kill()


def test_a_robot_refuses_to_start_when_a_planner_sends_another_command_type(
    tmp_path: Path,
) -> None:
    lab_copy(tmp_path)
    with (tmp_path / "ceddp.toml").open("a") as toml:
        toml.write('\n[[planners]]\nclass = "tests.integration.team_nodes:StampedDriver"\n')
    env = {"PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    ceddp = Process("ceddp", ["-m", "arpz.ceddp", "--config", "ceddp.toml"], tmp_path, env)
    try:
        ceddp.wait_for("ready on")
        done = subprocess.run(
            [sys.executable, "-m", "arpz.robot", "--config", "robot.toml"],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert ceddp.interrupt() == 0
    finally:
        ceddp.kill()
    assert done.returncode == 2, done.stderr
    assert (
        "planner StampedDriver sends cmd_vel as geometry_msgs/msg/TwistStamped, its actuator "
        "takes geometry_msgs/msg/Twist" in done.stderr
    ), done.stderr
