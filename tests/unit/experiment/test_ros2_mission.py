"""The pure parts of the hallway mission over ROS 2 (arpz.experiment.ros2.mission*): pacing, the
acknowledgement bookkeeping, the yaw, the verdict letters, the cells and their arpz spec, the
results table and figure. No rclpy and no lab here (tests/integration/test_ros2_mission.py)."""

from __future__ import annotations

import math
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from arpz.ceddp.optimiser import QosLimits, solve_closed
from arpz.experiment.ros2.mission import CpuSampler, arpz_spec, cells_of
from arpz.experiment.ros2.mission_cell import MissionCell, node_args, ros_env
from arpz.experiment.ros2.mission_parts import (
    AckTracker,
    Pacer,
    verdict_letter,
    yaw_of,
    yaw_quaternion,
)
from arpz.experiment.ros2.mission_results import (
    append_row,
    arpz_row,
    draw_figure,
    read_rows,
    tally,
    verdict_table,
)
from arpz.experiment.spec import spec_from_dict
from arpz.lab.fleet import process_cpu_s
from tests.support import wait_until


def test_a_pacer_is_due_once_a_period_and_skips_what_a_late_loop_missed() -> None:
    pacer = Pacer(10.0, 0.0)
    assert pacer.due(0.0) and not pacer.due(0.05)
    assert pacer.due(0.1) and not pacer.due(0.15)
    # one period late: caught up at once (the next is due right after)
    assert pacer.due(0.31) and pacer.due(0.31) and not pacer.due(0.31)
    # five periods late: the missed ones are skipped and counted, not replayed
    assert pacer.due(0.95) and not pacer.due(0.95)
    assert pacer.skipped == 5
    assert pacer.next_s == pytest.approx(1.0)


def test_the_ack_tracker_reports_the_oldest_unacknowledged_send() -> None:
    tracker = AckTracker()
    assert tracker.poll(True) is None
    tracker.sent(1.0)
    tracker.sent(1.05)  # the oldest stays 1.0
    assert tracker.poll(False) == 1.0
    tracker.sent(1.1)
    assert tracker.poll(True) is None
    tracker.sent(1.15)
    assert tracker.poll(False) == 1.15
    assert (tracker.polls, tracker.unacknowledged_polls) == (4, 2)


@pytest.mark.parametrize("theta", [0.0, 0.5, -1.2, math.pi / 2, 3.1, -3.1])
def test_yaw_survives_the_quaternion(theta: float) -> None:
    assert yaw_of(*yaw_quaternion(theta)) == pytest.approx(theta)


def test_a_process_cpu_time_comes_from_proc() -> None:
    sum(i * i for i in range(200_000))
    assert process_cpu_s(os.getpid()) > 0.0
    assert process_cpu_s(2**22 + 12345) == 0.0  # no such process


@pytest.mark.parametrize(
    ("result", "letter"),
    [
        ({"mission": "success", "reason": "all home"}, "S"),
        ({"mission": "failure", "failure": "timeout", "reason": "timeout: ..."}, "T"),
        ({"mission": "failure", "reason": "collision: robot1 touched a wall"}, "C"),
        ({"mission": "failure", "failure": "phantom_obstacle", "reason": "x"}, "P"),
        ({"mission": "failure", "reason": "no verdict: the mission never started"}, "N"),
        (None, "N"),
    ],
)
def test_verdict_letters(result: dict[str, str] | None, letter: str) -> None:
    assert verdict_letter(result) == letter


def test_an_opt_cell_runs_at_the_optimisers_rate_and_depth() -> None:
    cell = MissionCell(500.0, None, "opt", "lab:loss-8")
    solution = solve_closed(QosLimits(rmax_hz=500.0, rmin_hz=1.0, dmax=5000), [10, 10, 10])
    assert cell.qos() == (solution.rate_hz, solution.depth) == (49.0, 489)
    assert cell.depth_label == "opt" and cell.slug == "r500_dopt_opt_loss-8_1"
    assert MissionCell(100.0, 1, "baseline", "lab:loss-8").qos() == (100.0, 1)


@pytest.mark.parametrize(
    ("depth", "config", "network"),
    [
        (None, "baseline", "lab:loss-8"),
        (1, "opt", "lab:loss-8"),
        (1, "lc", "lab:loss-8"),
        (1, "baseline", "wifi-bad"),
        (1, "baseline", "lab:no-such-profile"),
    ],
)
def test_cells_that_cannot_run_are_refused(depth: int | None, config: str, network: str) -> None:
    with pytest.raises(ValueError):
        MissionCell(100.0, depth, config, network)


def test_the_grid_and_the_node_arguments() -> None:
    cells = cells_of([100, 200], [1, 1000], ["baseline", "opt"], "lab:loss-8", 2, time_limit_s=60)
    assert len(cells) == 2 * (2 + 1) * 2
    cell = cells[0]
    planner = node_args(cell, "planner", Path("/w/planner.json"))
    assert planner[:4] == ["-m", "arpz.experiment.ros2.mission_node", "--role", "planner"]
    assert "--rate-hz" in planner and planner[planner.index("--depth") + 1] == "1"
    robot = node_args(cell, "robot", Path("/w/robot2.json"), robot="robot2", seed=102)
    assert robot[-4:] == ["--robot", "robot2", "--seed", "102"]
    env = ros_env(Path("/w"), 42, ["10.0.0.1", "10.0.0.2"])
    assert env["FASTDDS_BUILTIN_TRANSPORTS"] == "UDPv4"
    assert env["ROS_STATIC_PEERS"] == "10.0.0.1;10.0.0.2" and env["ROS_DOMAIN_ID"] == "42"


@pytest.mark.parametrize("config", ["baseline", "opt"])
def test_the_arpz_spec_of_a_cell_is_a_one_cell_lab_mission(config: str) -> None:
    cell = MissionCell(200.0, 1000 if config == "baseline" else None, config, "lab:loss-8")
    spec = spec_from_dict(tomllib.loads(arpz_spec(cell, "t")), source="test")
    (only,) = spec.cells()
    assert (only.rmax_hz, str(only.depth), only.config, only.network) == (
        200.0,
        cell.depth_label,
        config,
        "lab:loss-8",
    )
    assert spec.mission is not None and spec.mission.world == "hallway_small"


def test_the_cpu_sampler_finds_a_process_by_its_config(tmp_path: Path) -> None:
    config = tmp_path / "runs" / "cell" / "robot1.toml"
    burn = "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.3: pass\n"
    proc = subprocess.Popen(
        [sys.executable, "-c", burn + "time.sleep(30)", "--config", str(config)]
    )
    sampler = CpuSampler(str(tmp_path / "runs"))
    try:

        def burnt() -> bool:
            sampler.sample()
            return sampler.totals().get("robot1", 0.0) >= 0.25

        wait_until(burnt, timeout_s=20, what="the process's CPU seen by the sampler")
    finally:
        proc.kill()
        proc.wait(timeout=10)
    assert set(sampler.stop()) == {"robot1"}


def _row(middleware: str, rmax: str, depth: str, config: str, verdict: str) -> dict[str, str]:
    return {
        "middleware": middleware,
        "rmax_hz": rmax,
        "depth": depth,
        "config": config,
        "network": "lab:loss-8",
        "repeat": "1",
        "status": "ok",
        "rate_hz": rmax,
        "qos_depth": depth,
        "verdict": verdict,
        "beam_loss_pct": "10",
        "beam_latency_ms_p99": "20",
        "cpu_ceddp_s": "12",
        "cpu_robots_s": "9",
    }


def test_results_table_and_figure(tmp_path: Path) -> None:
    csv = tmp_path / "results.csv"
    rows = [
        _row("ros2", "100", "1", "baseline", "S"),
        _row("arpz", "100", "1", "baseline", "S"),
        _row("ros2", "1000", "1", "baseline", "T"),
        _row("arpz", "1000", "opt", "opt", "C"),
    ]
    for row in rows:
        append_row(csv, row)
    back = read_rows(csv)
    assert len(back) == 4 and back[2]["verdict"] == "T" and back[0]["error"] == ""
    counts = tally(back)
    assert counts[("ros2", (1000.0, "1", "baseline"))]["T"] == 1
    table = verdict_table(back)
    assert (
        "| 100 | no opt., depth 1 | 100 Hz, 1 | 1S | 1S | 10.0 % | 10.0 % | 20 ms | 20 ms | "
        "12 + 9 | 12 + 9 |"
    ) in table
    assert "| 1000 | OPT (Opt(R), Opt(D)) |" in table
    png = draw_figure(back, tmp_path / "mission.png", title="t")
    assert png.stat().st_size > 10_000


def test_a_csv_written_before_a_column_existed_is_rewritten_with_it(tmp_path: Path) -> None:
    csv = tmp_path / "results.csv"
    csv.write_text("middleware,rmax_hz,verdict\nros2,100,S\n", encoding="utf-8")
    append_row(csv, _row("arpz", "200", "1", "baseline", "T"))
    rows = read_rows(csv)
    assert [(r["middleware"], r["rmax_hz"], r["verdict"]) for r in rows] == [
        ("ros2", "100", "S"),
        ("arpz", "200", "T"),
    ]
    assert rows[0]["beam_latency_ms_p99"] == "" and rows[1]["beam_latency_ms_p99"] == "20"


def test_an_arpz_results_row_becomes_ours() -> None:
    row = {
        "rmax_hz": "500",
        "depth": "opt",
        "config": "opt",
        "network": "lab:loss-8",
        "repeat": "1",
        "status": "ok",
        "mission": "failure",
        "mission_reason": "collision: robot2 touched a wall",
        "mission_duration_s": "20.5",
        "samples_sent": "100",
        "samples_received": "90",
        "samples_lost": "10",
        "commands_written": "400",
        "commands_delivered": "399",
        "rate_hz": "49",
        "qos_depth": "489",
    }
    ours = arpz_row(row, {"ceddp": 10.0, "robot1": 2.0, "robot2": 3.0}, wall_s=40.0)
    assert ours["verdict"] == "C" and ours["middleware"] == "arpz"
    assert (ours["beams_lost"], ours["commands_received"]) == ("10", "399")
    assert (ours["cpu_ceddp_s"], ours["cpu_robots_s"], ours["wall_s"]) == (10.0, 5.0, 40.0)
