"""ROS 2 cells beside arpz's: the spec's ``middlewares``, the cells it makes, results.csv's
``middleware`` column (older files read as arpz), the ROS 2 row's reconciliation and the report
with both middlewares side by side."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import pytest

from arpz.experiment import fleet
from arpz.experiment.fleet import INITIAL_OPT_DEPTH, check_cells, configured_qos
from arpz.experiment.report import _grouped, series_label, write_report
from arpz.experiment.results import COLUMNS, append_row, done_keys, read_rows
from arpz.experiment.ros2 import machines_cell
from arpz.experiment.ros2.machines_row import CellCounters, CountersError, ros2_row
from arpz.experiment.runner import middleware_plan
from arpz.experiment.spec import Cell, ExperimentSpec, SpecError, spec_from_dict


def _spec(**fields: Any) -> ExperimentSpec:
    raw: dict[str, Any] = {
        "name": "t",
        "rmax_hz": [100],
        "depths": [1, 10],
        "configs": ["baseline", "opt"],
        "networks": ["lab:loss-8"],
        "middlewares": ["arpz", "ros2"],
    }
    raw.update(fields)
    return spec_from_dict(raw, source="test")


def test_without_middlewares_every_cell_is_arpz_as_before() -> None:
    spec = ExperimentSpec(
        name="t", rmax_hz=[100.0], depths=[1], configs=["baseline"], networks=["wifi-bad"]
    )
    (cell,) = spec.cells()
    assert cell.middleware == "arpz"
    assert cell.slug == "r100_d1_baseline_wifi-bad_1"
    assert cell.key == ("100", "1", "baseline", "1", "wifi-bad", "arpz")


def test_ros2_cells_interleave_with_arpz_and_skip_arpz_features() -> None:
    spec = _spec(configs=["baseline", "lc", "opt", "lc+opt"], repeats=2)
    cells = spec.cells()
    assert [(c.config, c.depth, c.repeat, c.middleware) for c in cells[:4]] == [
        ("baseline", 1, 1, "arpz"),
        ("baseline", 1, 1, "ros2"),
        ("baseline", 1, 2, "arpz"),
        ("baseline", 1, 2, "ros2"),
    ]
    ros2 = {c.config for c in cells if c.middleware == "ros2"}
    assert ros2 == {"baseline", "opt"}
    assert {c.config for c in cells if c.middleware == "arpz"} == {
        "baseline",
        "lc",
        "opt",
        "lc+opt",
    }
    assert spec.middleware_configs() == {
        "arpz": ["baseline", "lc", "opt", "lc+opt"],
        "ros2": ["baseline", "opt"],
    }
    plan = "\n".join(middleware_plan(spec))
    assert "ros2: baseline, opt (not lc, lc+opt: arpz features)" in plan
    assert cells[1].slug.startswith("ros2_") and ", ros2" in cells[1].label


@pytest.mark.parametrize(
    ("fields", "needle"),
    [
        ({"networks": ["wifi-bad"]}, "kernel lab only"),
        ({"robot_networks": {"robot2": "lan"}}, "kernel lab only"),
        ({"configs": ["lc", "lc+cc"]}, "runs on ros2"),
        ({"middlewares": ["dds"]}, "unknown middleware"),
        ({"middlewares": ["ros2", "ros2"]}, "twice"),
        ({"middlewares": []}, "at least one"),
    ],
)
def test_what_ros2_cells_cannot_run_is_a_spec_error(fields: dict[str, Any], needle: str) -> None:
    with pytest.raises(SpecError, match=needle):
        _spec(**fields)


def test_ros2_opt_runs_fixed_at_the_optimisers_r_and_d() -> None:
    spec = _spec()
    solution = fleet.optimiser_solution(spec, 100.0)
    ros2 = Cell(100.0, "opt", "opt", 1, "lab:loss-8", "ros2")
    arpz = Cell(100.0, "opt", "opt", 1, "lab:loss-8", "arpz")
    assert configured_qos(spec, ros2) == (float(solution.rate_hz), int(solution.depth))
    # arpz's CEDDP assigns them live; its robots start at Opt(R) with ROS 2's default depth
    assert configured_qos(spec, arpz) == (float(solution.rate_hz), INITIAL_OPT_DEPTH)


def test_ros2_not_installed_is_said_before_running(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(machines_cell.importlib.util, "find_spec", lambda name: None)
    assert "pip install 'arpz[ros2]'" in (machines_cell.ros2_missing() or "")
    with pytest.raises(SpecError, match=r"arpz\[ros2\]"):
        check_cells(_spec())


def _old_row() -> dict[str, str]:
    return {
        "experiment": "old",
        "rmax_hz": "100",
        "depth": "1",
        "config": "baseline",
        "repeat": "1",
        "network": "wifi-bad",
        "status": "ok",
        "samples_sent": "10",
    }


def test_results_without_the_middleware_column_read_as_arpz_and_resume(tmp_path: Path) -> None:
    path = tmp_path / "results.csv"
    old = [c for c in COLUMNS if c not in ("middleware", "cpu_s_ceddp", "cpu_s_robots")]
    with path.open("w", newline="", encoding="utf-8") as handle:
        writer = csv.DictWriter(handle, fieldnames=old, lineterminator="\n")
        writer.writeheader()
        writer.writerow({c: _old_row().get(c, "") for c in old})
    (row,) = read_rows(path)
    assert row["middleware"] == "arpz"
    arpz = Cell(100.0, 1, "baseline", 1, "wifi-bad")
    ros2 = Cell(100.0, 1, "baseline", 1, "wifi-bad", "ros2")
    assert done_keys(path) == {arpz.key}
    append_row(path, {**_old_row(), "middleware": "ros2", "cpu_s_ceddp": 1.5})
    with path.open(newline="", encoding="utf-8") as handle:
        assert tuple(next(csv.reader(handle))) == COLUMNS
    assert done_keys(path) == {arpz.key, ros2.key}
    assert {r["middleware"] for r in read_rows(path)} == {"arpz", "ros2"}


def _counters(*, taken: int = 90, sent: int = 100) -> CellCounters:
    robot1 = {
        "topics": {"lidar": {"produced": sent, "sent": sent}},
        "window_s": 1.0,
        "hello": {"sent": 10, "received": 8, "lost": 2, "rtt_ms_p50": 3.0, "rtt_ms_p99": 9.0},
        "hops_received": 9,
    }
    robot2 = {"topics": {"pir": {"produced": 50, "sent": 50}}, "window_s": 1.0, "hops_received": 9}
    ceddp = {
        "robots": {
            "robot1": {
                "latency_ms_p50": 1.0,
                "latency_ms_p99": 4.0,
                "topics": {"lidar": {"received": taken}},
            },
            "robot2": {
                "latency_ms_p50": 2.0,
                "latency_ms_p99": 3.0,
                "topics": {"pir": {"received": 50}},
            },
        },
        "hops_written": {"robot1": 9, "robot2": 10},
    }
    return CellCounters(
        nodes={"ceddp": ceddp, "robot1": robot1, "robot2": robot2},
        cpu_s={"ceddp": 1.25, "robot1": 0.5, "robot2": 0.25},
        link_seen=1000,
        link_dropped=80,
        bytes_up=90_000,
        measured_s=1.0,
        wall_s=9.0,
        rate_hz=100.0,
        depth=10,
    )


def test_a_ros2_row_reconciles_its_nodes_counters() -> None:
    cell = Cell(100.0, 10, "baseline", 1, "lab:loss-8", "ros2")
    row = ros2_row(cell, _counters(), experiment="t")
    assert row["middleware"] == "ros2"
    assert (row["samples_sent"], row["samples_received"], row["samples_lost"]) == (150, 140, 10)
    assert row["loss_pct"] == 20.0 and row["latency_ms_p50"] == 3.0
    assert row["sample_latency_ms_p50"] == 2.0  # the worst robot's
    assert (row["cpu_s_ceddp"], row["cpu_s_robots"]) == (1.25, 0.75)
    assert row["hello_hops_written"] == 19 and row["hello_hops_lost"] == 1
    assert row["rate_hz_achieved"] == 75.0 and row["link_loss_pct"] == 8.0
    assert set(row) <= set(COLUMNS)


def test_a_ros2_row_that_does_not_reconcile_is_an_error() -> None:
    cell = Cell(100.0, 10, "baseline", 1, "lab:loss-8", "ros2")
    with pytest.raises(CountersError, match="took 120 samples"):
        ros2_row(cell, _counters(taken=120), experiment="t")
    broken = _counters()
    del broken.nodes["ceddp"]
    with pytest.raises(CountersError, match="CEDDP"):
        ros2_row(cell, broken, experiment="t")


def _row(middleware: str, config: str, depth: str, loss: float, repeat: int) -> dict[str, Any]:
    return {
        "experiment": "t",
        "rmax_hz": "1000",
        "depth": depth,
        "config": config,
        "repeat": repeat,
        "network": "lab:loss-8",
        "middleware": middleware,
        "status": "ok",
        "latency_ms_p50": 10.0 + loss,
        "loss_pct": loss,
        "hello_sent": 10,
        "hello_received": 10,
        "hello_lost": 0,
        "sample_loss_pct": loss,
        "sample_latency_ms_p50": 2.0,
        "samples_produced": 100,
        "samples_sent": 100,
        "samples_received": 100,
        "samples_lost": 0,
        "final_reports": 3,
        "rate_hz": 1000.0,
        "qos_depth": 1,
        "cpu_s_ceddp": 1.0,
        "cpu_s_robots": 2.0,
        "wall_s": 10.0,
    }


def test_the_report_puts_both_middlewares_side_by_side(tmp_path: Path) -> None:
    results = tmp_path / "results.csv"
    for repeat in (1, 2):
        for middleware, loss in (("arpz", 1.0), ("ros2", 20.0)):
            append_row(results, _row(middleware, "baseline", "1", loss + repeat, repeat))
            append_row(results, _row(middleware, "opt", "opt", loss / 2, repeat))
    rows = read_rows(results)
    assert {key[3] for key in _grouped(rows)} == {
        "arpz|baseline",
        "arpz|opt",
        "ros2|baseline",
        "ros2|opt",
    }
    assert series_label("ros2|opt") == "ROS 2 OPT" and series_label("opt") == "OPT"
    paths = write_report(tmp_path)
    report = paths[0].read_text()
    assert "| DEPTH | arpz no opt. | arpz OPT | ROS 2 no opt. | ROS 2 OPT |" in report
    assert "31.5 [31-32] ms, 22 [21-22] %" in report  # ROS 2's Hello over its two repeats
    assert "CPU CEDDP 1 s, robots 2 s" in report
    assert (tmp_path / "figures" / "experiment_loss.png").exists()


def test_a_report_of_arpz_results_names_no_middleware(tmp_path: Path) -> None:
    results = tmp_path / "results.csv"
    append_row(results, _row("arpz", "baseline", "1", 1.0, 1))
    rows = read_rows(results)
    assert {key[3] for key in _grouped(rows)} == {"baseline"}
    report = write_report(tmp_path)[0].read_text()
    assert "| DEPTH | no opt. |" in report
