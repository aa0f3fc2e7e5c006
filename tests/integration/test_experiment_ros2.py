"""A ROS 2 cell beside an arpz cell: seed 001's application in real rclpy nodes over Fast DDS
(arpz.experiment.ros2) and arpz's fleet, each in a kernel lab of its own over the same lossy
profile, their rows reconciled and their bytes seen on the lab's links (no shared memory).
Root only (tests/lab_support.py); ROS 2 comes with the test extra (``arpz[ros2]``)."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest

from arpz.experiment.ros2.machines_cell import ros2_missing
from arpz.experiment.runner import run_cell
from arpz.experiment.spec import ExperimentSpec
from tests.lab_support import require_lab

pytestmark = [pytest.mark.integration, pytest.mark.slow]

#: the least a sample takes on the wire: PointStamped in CDR is about 48 bytes before RTPS's
#: own headers; an arpz sample (msgpack, batched by Zenoh) more than 10
MIN_BYTES_PER_SAMPLE = {"ros2": 40, "arpz": 10}


def _check(row: dict[str, Any]) -> None:
    middleware = row["middleware"]
    assert row["status"] == "ok", (middleware, row["error"])
    n = {k: int(row[k] or 0) for k in row if k.startswith(("samples_", "hello_"))}
    assert n["hello_sent"] > 0, row
    assert n["hello_sent"] == n["hello_received"] + n["hello_lost"], row
    assert n["samples_received"] > 0, row
    assert n["samples_sent"] == n["samples_received"] + n["samples_lost"], row
    assert n["samples_produced"] == n["samples_sent"] + n["samples_held_back"], row
    assert float(row["cpu_s_ceddp"]) > 0 and float(row["cpu_s_robots"]) > 0, row
    # the samples crossed the kernel links (with shared memory they would not): the robots'
    # uplinks carried at least their bytes, and the profile dropped frames on them
    bytes_up = int(row["link_bytes_up"])
    assert bytes_up >= n["samples_received"] * MIN_BYTES_PER_SAMPLE[middleware], row
    assert int(row["link_dropped"]) > 0 and int(row["link_datagrams"]) > 100, row


def test_a_ros2_cell_and_an_arpz_cell_side_by_side_in_the_lab(tmp_path: Path) -> None:
    require_lab()
    missing = ros2_missing()
    assert missing is None, missing  # the test extra installs ROS 2: never a skip
    spec = ExperimentSpec(
        name="vs-ros2-cell",
        rmax_hz=[100.0],
        depths=[10],
        configs=["baseline"],
        networks=["lab:loss-8"],
        middlewares=["arpz", "ros2"],
        presets=["machine1", "machine3"],
        hello_relay="robot2",
        duration_s=2.0,
    )
    cells = spec.cells()
    assert [c.middleware for c in cells] == ["arpz", "ros2"]
    # two labs of their own, at once: the test costs the longer cell, not both
    with ThreadPoolExecutor(max_workers=2) as pool:
        rows = list(pool.map(lambda cell: run_cell(spec, cell, tmp_path / cell.middleware), cells))
    for row in rows:
        _check(row)
    ros2 = rows[1]
    # the rate the timers reached is reported (not asserted: rclpy's timers starve on a loaded
    # 2-core machine, 6 Hz of 100 beside another grid)
    assert float(ros2["rate_hz_achieved"]) > 0, ros2
    # every node wrote its counters, kept beside the cell's timeline
    kept = {p.name for p in (tmp_path / "ros2" / "runs" / cells[1].slug).iterdir()}
    assert {"ceddp.json", "robot1.json", "robot2.json", "lab_timeline.jsonl"} <= kept
