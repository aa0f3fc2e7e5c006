"""Two CEDDP routers in one Zenoh mesh, the fleet partitioned by key space (issue 8)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from tests.integration.fleet import Process, robots, write_robot
from tests.support import free_port, wait_until

pytestmark = pytest.mark.integration


def ceddp_config(
    tmp: Path, name: str, endpoint: str, partition: str, *, connect: str = "", qos: bool = False
) -> Path:
    path = tmp / f"{name}.toml"
    text = (
        f'fleet = "mesh"\nlisten = ["{endpoint}"]\npartition = "{partition}"\n'
        f'rrd = "{(tmp / f"{name}.rrd").as_posix()}"\n'
        f'summary_json = "{(tmp / f"{name}.json").as_posix()}"\nmetrics_period_s = 0.2\n'
        # written this often while running too: the test polls it
        "summary_period_s = 0.2\n"
    )
    if connect:
        text += f'connect = ["{connect}"]\n'
    if qos:
        text += "[qos]\nenabled = true\nrmax_hz = 100.0\n"
    path.write_text(text)
    return path


def _summary(path: Path) -> dict[str, Any]:
    """A CEDDP's latest summary (written atomically); empty before the first."""
    try:
        summary: dict[str, Any] = json.loads(path.read_text())
    except FileNotFoundError:
        return {}
    return summary


def test_two_ceddps_share_the_fleet_by_key_space(tmp_path: Path) -> None:
    def each_ceddp_has_its_robots_and_all_applied_the_qos() -> bool:
        east, west = _summary(tmp_path / "east.json"), _summary(tmp_path / "west.json")
        if not east or not west:
            return False
        arrived = all(
            summary["robots"].get(robot, {}).get("received", 0) > 0
            for summary, robot in ((east, "e1"), (east, "e2"), (west, "w1"))
        )
        acks = (east["qos"] or {}).get("acks", {})
        applied = {robot for robot, ack in acks.items() if ack["status"] == "applied"}
        return arrived and applied == {"e1", "e2", "w1"}

    east = f"tcp/127.0.0.1:{free_port()}"
    west = f"tcp/127.0.0.1:{free_port()}"
    a = Process(
        "east",
        [
            "-m",
            "arpz.ceddp",
            "--config",
            str(ceddp_config(tmp_path, "east", east, "e$*", qos=True)),
        ],
        tmp_path,
    )
    b = Process(
        "west",
        [
            "-m",
            "arpz.ceddp",
            "--config",
            str(ceddp_config(tmp_path, "west", west, "w$*", connect=east)),
        ],
        tmp_path,
    )
    try:
        a.wait_for("ready on")
        b.wait_for("ready on")
        configs = [
            write_robot(tmp_path, "e1", east, preset="machine1", fleet="mesh"),
            write_robot(tmp_path, "w1", west, preset="machine2", fleet="mesh"),
            # an east robot on the west router: its data must cross the mesh to its CEDDP
            write_robot(tmp_path, "e2", west, preset="machine3", fleet="mesh"),
        ]
        with robots(tmp_path, configs) as procs:
            wait_until(
                each_ceddp_has_its_robots_and_all_applied_the_qos,
                what="each CEDDP to receive its robots' samples and all three to apply the QoS",
            )
            for proc in procs:
                assert proc.interrupt() == 0, proc.output()
        assert b.interrupt() == 0, b.output()
        assert a.interrupt() == 0, a.output()
    finally:
        a.kill()
        b.kill()
    east_summary = json.loads((tmp_path / "east.json").read_text())
    west_summary = json.loads((tmp_path / "west.json").read_text())
    for summary, mine, others in (
        (east_summary, ("e1", "e2"), ("w1",)),
        (west_summary, ("w1",), ("e1", "e2")),
    ):
        for robot in mine:
            row = summary["robots"][robot]
            assert row["received"] > 0 and row["final_stats"], (robot, row)
            assert row["sent"] == row["received"] + row["lost"] and row["lost"] == 0
        for robot in others:
            # fleet-wide: the CEDDP knows the robot and its own counters, not its samples
            row = summary["robots"][robot]
            assert row["received"] == 0 and row["final_stats"], (robot, row)
    # QoS stays fleet-wide: one optimiser counted all three robots and all three applied it
    qos = east_summary["qos"]
    assert any(set(a["topics_per_robot"]) == {"e1", "e2", "w1"} for a in qos["assignments"])
    assert {robot for robot, ack in qos["acks"].items() if ack["status"] == "applied"} == {
        "e1",
        "e2",
        "w1",
    }
