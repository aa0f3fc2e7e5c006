"""``python -m arpz.tools.topic`` against a real fleet: a real CEDDP (the router) and two robot
processes, each subcommand run as a subprocess with ``--json``, its output checked against the
fleet's configuration and its own counters.

robot1: lidar and IMU at 20 Hz with the local cache off (every reading is sent, so the rate on
the wire is the configured one), a 160x120 camera at 2 Hz (frames through the channel), and a
sensor QoS of its own (deadline 0.5 s) that ``info`` must show. robot2: seed 001's machine2
preset at 10 Hz.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from arpz.core.endpoints import frame_fragment_bytes
from arpz.core.rosmsg.types import ros_type_for
from arpz.robot.sensors import PRESETS
from tests.integration.fleet import Process, ceddp, robots, write_robot
from tests.support import wait_until

pytestmark = pytest.mark.integration

FLEET = "topictest"
RATE_HZ = 20.0
CAMERA_HZ = 2.0
CAMERA_BYTES = 160 * 120 * 3
ROBOT1_SENSORS = {"lidar": "lidar", "imu": "imu", "front": "camera"}


@dataclass
class Fleet:
    endpoint: str
    server: Process
    cwd: Path


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Fleet]:
    tmp = tmp_path_factory.mktemp("topic")
    with ceddp(tmp, fleet=FLEET) as (server, endpoint):
        robot1 = tmp / "robot1.toml"
        robot1.write_text(
            f'robot_id = "robot1"\nfleet = "{FLEET}"\nconnect = ["{endpoint}"]\n'
            "stats_period_s = 0.2\n"
            "[local_cache]\nenabled = false\n"
            "[sensor_qos]\ndeadline_s = 0.5\ndepth = 20\n"
            f'[[sensors]]\nname = "lidar"\nkind = "lidar"\nrate_hz = {RATE_HZ}\n'
            f'[[sensors]]\nname = "imu"\nkind = "imu"\nrate_hz = {RATE_HZ}\n'
            f'[[sensors]]\nname = "front"\nkind = "camera"\nrate_hz = {CAMERA_HZ}\n'
            "options = { width = 160, height = 120 }\n"
        )
        robot2 = write_robot(tmp, "robot2", endpoint, preset="machine2", rate_hz=10, fleet=FLEET)
        with robots(tmp, [robot1, robot2]):
            joined = ("robot robot1 joined", "robot robot2 joined")
            wait_until(lambda: all(j in server.output() for j in joined), what="both robots")
            yield Fleet(endpoint, server, tmp)


def topic(fleet: Fleet, *args: str, timeout_s: float = 30) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "arpz.tools.topic",
            *args,
            "--connect",
            fleet.endpoint,
            "--fleet",
            FLEET,
        ],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        cwd=fleet.cwd,
        check=False,
    )


def json_lines(run: subprocess.CompletedProcess[str]) -> list[dict[str, Any]]:
    assert run.returncode == 0, run.stderr
    return [json.loads(line) for line in run.stdout.splitlines() if line.strip()]


def final(lines: list[dict[str, Any]]) -> dict[str, Any]:
    assert lines and lines[-1].get("final") is True, lines[-3:]
    return lines[-1]


def test_list_has_every_configured_topic_with_its_type_and_writer(fleet: Fleet) -> None:
    run = topic(fleet, "list", "--json")
    assert run.returncode == 0, run.stderr
    graph = json.loads(run.stdout)
    topics = {t["name"]: t for t in graph["topics"]}
    nodes = {n["name"]: n for n in graph["nodes"]}
    assert {n: (v["alive"], v["mode"]) for n, v in nodes.items()} == {
        "ceddp": (True, "channel"),
        "robot1": (True, "channel"),
        "robot2": (True, "channel"),
    }
    expected = {f"/robot1/{name}": kind for name, kind in ROBOT1_SENSORS.items()}
    expected |= {f"/robot2/{kind}": kind for kind in PRESETS["machine2"]}
    for name, kind in expected.items():
        assert name in topics, f"{name} missing from {sorted(topics)}"
        row = topics[name]
        assert row["type"] == ros_type_for(kind), row
        assert row["kind"] == kind
        assert row["arpz_type"] == ("LargeSample" if kind == "camera" else "Sample")
        owner = name.split("/")[1]
        assert [w["node"] for w in row["writers"]] == [owner]
        assert [r["node"] for r in row["readers"]] == ["ceddp"]
    assert topics["/robot1/front"]["key"] == f"arpz/{FLEET}/robot/robot1/frames/front"
    assert topics["/robot1/imu"]["announced_rate_hz"] == RATE_HZ
    assert topics["/robot1/imu"]["measured_rate_hz"] == pytest.approx(RATE_HZ, rel=0.2)
    # the CEDDP -> robot command topics and the CEDDP's own keys
    for robot in ("robot1", "robot2"):
        hello = topics[f"/{robot}/cmd/hello"]
        assert [w["node"] for w in hello["writers"]] == ["ceddp"]
        assert [r["node"] for r in hello["readers"]] == [robot]
        assert topics[f"/{robot}/stats"]["arpz_type"] == "RobotStats"
    assert topics["/ceddp/stats"]["arpz_type"] == "CeddpStats"


def test_info_shows_each_writers_configured_qos_and_the_match(fleet: Fleet) -> None:
    run = topic(fleet, "info", "robot1/imu", "--json")
    assert run.returncode == 0, run.stderr
    info = json.loads(run.stdout)
    assert info["name"] == "/robot1/imu"
    [writer] = info["writers"]
    assert writer["qos"] == {
        "reliability": "reliable",
        "durability": "volatile",
        "liveliness": "automatic",
        "deadline_s": 0.5,  # robot1's [sensor_qos]
        "lease_duration_s": 0.0,
    }
    [reader] = info["readers"]
    assert reader["node"] == "ceddp" and reader["qos"]["deadline_s"] == 0.0
    assert info["matches"] == [
        {"writer": writer["guid"], "reader": reader["guid"], "compatible": True, "policy": None}
    ]
    # robot2 runs the default sensor QoS: no deadline
    other = json.loads(topic(fleet, "info", "/robot2/ultrasonic", "--json").stdout)
    assert other["writers"][0]["qos"]["deadline_s"] == 0.0


def test_echo_decodes_plausible_values_and_counts_them(fleet: Fleet) -> None:
    lines = json_lines(topic(fleet, "echo", "/robot1/lidar", "--duration", "3", "--json"))
    summary = final(lines)
    messages = lines[:-1]
    assert len(messages) >= 0.6 * RATE_HZ * 3
    seqs = [m["message"]["seq"] for m in messages]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    for m in messages:
        sample = m["message"]
        assert sample["writer"].startswith("robot1:")
        assert 0.5 <= sample["value"] <= 6.5  # a wall at 2-6 m, or a person passing at 0.8 m
    counters = summary["counters"]
    assert counters["delivered"] == len(messages)
    # BEST_EFFORT reader on loopback: whatever it missed is counted, and it is little
    assert counters["lost"] == (seqs[-1] - seqs[0] + 1) - len(messages)
    assert counters["lost"] <= 0.05 * len(messages)
    assert counters["retransmitted"] == 0


def test_echo_of_a_camera_prints_a_summary_per_frame(fleet: Fleet) -> None:
    run = topic(fleet, "echo", "/robot1/front", "--count", "2", "--duration", "8", "--json")
    lines = json_lines(run)
    frames = [line for line in lines if "message" in line]
    assert len(frames) == 2 and final(lines)["counters"]["delivered"] >= 2
    for frame in frames:
        value = frame["message"]["value"]
        assert value["bytes"] == CAMERA_BYTES and value["pixels"] == CAMERA_BYTES // 3
        # as many fragments as the robot cut for its link: over TCP one of 60 KiB holds the
        # whole 57 600-byte frame and its header; over UDP it would be 46 of 1280 B
        size = frame_fragment_bytes([fleet.endpoint])
        assert (
            -(-CAMERA_BYTES // size)
            <= frame["frame"]["fragments"]
            <= -(-(CAMERA_BYTES + 100) // size)
        )
    assert len(run.stdout) < 10_000  # no megabytes of numbers


def test_hz_is_the_configured_rate(fleet: Fleet) -> None:
    summary = final(json_lines(topic(fleet, "hz", "/robot1/imu", "--duration", "3", "--json")))
    assert summary["rate_hz"] == pytest.approx(RATE_HZ, rel=0.2)
    assert 0 < summary["period_min_s"] <= 1 / RATE_HZ <= summary["period_max_s"]
    assert summary["counters"]["matched_writers"] == 1


def test_bw_of_the_camera(fleet: Fleet) -> None:
    summary = final(json_lines(topic(fleet, "bw", "/robot1/front", "--duration", "3", "--json")))
    # the reassembled message: the frame's bytes and a few dozen bytes of Sample around them
    assert CAMERA_BYTES < summary["size_mean"] < CAMERA_BYTES + 100
    assert summary["bytes_per_s"] == pytest.approx(CAMERA_HZ * summary["size_mean"], rel=0.3)


def test_delay_is_small_and_corrected_by_the_clock_offsets(fleet: Fleet) -> None:
    summary = final(json_lines(topic(fleet, "delay", "/robot1/imu", "--duration", "3", "--json")))
    assert summary["window"] >= 0.6 * RATE_HZ * 2
    assert -0.005 < summary["delay_min_s"] <= summary["delay_mean_s"] < 0.5
    assert summary["corrected"] is True, summary["clock"]


def test_an_unknown_topic_is_an_error_with_close_matches(fleet: Fleet) -> None:
    run = topic(fleet, "hz", "/robot1/imuu", "--duration", "1")
    assert run.returncode == 2
    assert "arpz topic: error: no topic '/robot1/imuu'" in run.stderr
    assert "did you mean /robot1/imu" in run.stderr


def test_ctrl_c_stops_a_stream_cleanly_with_its_counters(fleet: Fleet) -> None:
    args = ["-m", "arpz.tools.topic", "hz", "/robot2/ultrasonic", "--json"]
    args += ["--connect", fleet.endpoint, "--fleet", FLEET]
    proc = subprocess.Popen(
        [sys.executable, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout is not None
        first = json.loads(proc.stdout.readline())  # the first second's figures: running
        assert first["messages"] > 0
        proc.send_signal(signal.SIGINT)
        rest, err = proc.communicate(timeout=10)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    summary = json.loads(rest.splitlines()[-1])
    assert summary["final"] is True and summary["counters"]["delivered"] == summary["messages"]
