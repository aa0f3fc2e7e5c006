"""Typed topics through the tools (issue 41): ``topic echo`` shows a typed message field by
field, ``record`` writes each typed topic as CDR of its own ROS 2 type (the lab's own type with
``--msg-path``) that independent readers decode whole, and ``play`` publishes the recording back
into a fleet whose CEDDP decodes every message, with no .msg file of its own needed by play."""

from __future__ import annotations

import json
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

from tests.integration.fleet import Process
from tests.integration.test_example_lab import lab_copy

pytestmark = pytest.mark.integration
TYPED = {
    "/robot1/gps": "sensor_msgs/msg/NavSatFix",
    "/robot1/battery": "sensor_msgs/msg/BatteryState",
    "/robot1/dock_state": "mylab/msg/DockState",
}


def tool(tmp_path: Path, *args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "arpz", *args],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def test_echo_record_and_play_carry_typed_topics_whole(tmp_path: Path) -> None:
    endpoint = lab_copy(tmp_path)
    ceddp = Process("ceddp", ["-m", "arpz.ceddp", "--config", "ceddp.toml"], tmp_path)
    try:
        ceddp.wait_for("ready on")
        robot = Process("robot1", ["-m", "arpz.robot", "--config", "robot.toml"], tmp_path)
        try:
            robot.wait_for("running")
            echo = tool(tmp_path, "topic", "echo", "/robot1/dock_state", "--connect", endpoint,
                        "--count", "1", "--msg-path", "msg", "--json")  # fmt: skip
            assert echo.returncode == 0, echo.stderr
            line = json.loads(echo.stdout.splitlines()[0])
            assert line["message"]["type"] == "mylab/msg/DockState"
            assert set(line["message"]["message"]) == {"header", "docked", "dock_id", "distance_m"}
            record = tool(tmp_path, "record", "--connect", endpoint, "--out", "lab.mcap",
                          "--duration", "6", "--msg-path", "msg")  # fmt: skip
            assert record.returncode == 0, record.stderr
            assert robot.interrupt() == 0
        finally:
            robot.kill()
        assert ceddp.interrupt() == 0
    finally:
        ceddp.kill()

    # read back by readers that share nothing with arpz's writer
    from mcap.reader import make_reader

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        from mcap_ros2.reader import read_ros2_messages

        counts: dict[str, int] = {}
        for message in read_ros2_messages(str(tmp_path / "lab.mcap")):
            counts[message.channel.topic] = counts.get(message.channel.topic, 0) + 1
            if message.channel.topic == "/robot1/gps":
                assert message.ros_msg.latitude == pytest.approx(51.4545, abs=1e-3)
            if message.channel.topic == "/robot1/dock_state":
                assert message.ros_msg.dock_id in ("", "dock-1")
    with (tmp_path / "lab.mcap").open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    schemas = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
    for topic, msg_type in TYPED.items():
        assert schemas[topic] == msg_type
        assert counts.get(topic, 0) > 0, (topic, counts)

    from rosbags.highlevel import AnyReader

    with AnyReader([tmp_path / "lab.mcap"]) as reader:
        decoded = sum(1 for c, _, raw in reader.messages() if reader.deserialize(raw, c.msgtype))
    assert decoded == sum(counts.values())

    # play it into a fresh fleet: its CEDDP decodes every typed message
    endpoint = lab_copy(tmp_path / "again")
    again = tmp_path / "again"
    ceddp = Process("ceddp", ["-m", "arpz.ceddp", "--config", "ceddp.toml"], again)
    try:
        ceddp.wait_for("ready on")
        play = tool(again, "play", str(tmp_path / "lab.mcap"), "--connect", endpoint, timeout=90)
        assert play.returncode == 0, play.stderr
        assert ceddp.interrupt() == 0
    finally:
        ceddp.kill()
    played = json.loads((again / "summary.json").read_text())["robots"]["robot1"]["topics"]
    for topic in ("gps", "battery", "dock_state"):
        row = played[topic]
        assert row["received"] > 0 and row["decode_errors"] == 0, (topic, row)
