"""The fleet load test's pure reductions: rows, reconciliation, fleet figures, the knee, files."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import pytest

from arpz.perf.fleet_report import (
    CeddpFigures,
    ProcessFigures,
    RobotRow,
    ceddp_figures,
    ceddp_knees,
    failures_of,
    find_knee,
    fleet_knee,
    fleet_point,
    format_run,
    over_the_knee,
    per_sample_us,
    result_dict,
    robot_rows,
    unavailable,
    write_robot_csv,
    write_sweep_csv,
)


def _summary(robots: dict[str, dict[str, Any]], partition: str = "*") -> dict[str, Any]:
    return {
        "partition": partition,
        "robots": robots,
        "ingest": {"channel": {"queue_dropped": 3, "nacks": 5, "duplicates": 7}},
    }


def _row(sent: int, received: int, lost: int, p99: float = 2.0) -> dict[str, Any]:
    return {
        "sent": sent,
        "received": received,
        "lost": lost,
        "final_stats": True,
        "latency_ms_p50": p99 / 4,
        "latency_ms_p99": p99,
        "staleness_ms_p99": p99 + 1,
    }


def test_rows_read_each_robot_from_the_ceddp_of_its_partition() -> None:
    east = _summary({"c0-r001": _row(100, 100, 0), "c1-r001": _row(5, 0, 0)}, "c0-$*")
    west = _summary({"c1-r001": _row(50, 48, 2), "c0-r001": _row(5, 0, 0)}, "c1-$*")
    rows = robot_rows(
        {"c0-r001": (0, 0), "c1-r001": (1, 1)},
        [east, west],
        {"c0-r001": {"sent": 100, "late_ticks": 4}},
    )
    assert [(r.robot, r.ceddp, r.sent, r.delivered, r.lost) for r in rows] == [
        ("c0-r001", 0, 100, 100, 0),
        ("c1-r001", 1, 50, 48, 2),
    ]
    assert rows[0].worker_sent == 100 and rows[0].late_ticks == 4
    assert rows[1].worker_sent is None
    assert all(r.reconciled for r in rows)
    assert failures_of(rows) == []


def test_a_robot_its_ceddp_never_saw_fails_loudly() -> None:
    rows = robot_rows({"c0-r001": (0, 0)}, [_summary({})], {"c0-r001": {"sent": 10}})
    assert rows[0].final_report is False and not rows[0].reconciled
    assert failures_of(rows) == ["c0-r001: its final report did not reach CEDDP 0"]


def test_failures_name_the_unaccounted_and_a_disagreement_with_the_agent() -> None:
    rows = robot_rows(
        {"c0-r001": (0, 0)}, [_summary({"c0-r001": _row(100, 90, 5)})], {"c0-r001": {"sent": 99}}
    )
    assert failures_of(rows) == [
        "c0-r001: sent 100 != delivered 90 + lost 5 (+5 unaccounted)",
        "c0-r001: the agent counted 99 sent, its final report 100",
    ]


def _rows(n: int, p99: float = 2.0, lost: int = 0) -> list[RobotRow]:
    robots = {f"c0-r{i:03d}": _row(1000, 1000 - lost, lost, p99 + i) for i in range(1, n + 1)}
    return robot_rows({name: (0, 0) for name in robots}, [_summary(robots)], {})


def _process(cores: float) -> ProcessFigures:
    return ProcessFigures(pid=1, cpu_cores=cores, cpu_cores_peak=cores, rss_mb=100, rss_peak_mb=120)


def test_fleet_point_aggregates_and_flags_a_generator_limited_run() -> None:
    rows = _rows(4)
    ceddp = ceddp_figures(0, _summary({}), rows, _process(0.5), 10.0, {"dashboard_dropped": 0})
    assert ceddp.delivered == 4000 and ceddp.delivered_per_s == 400.0
    assert ceddp.latency_ms_p99 == 6.0  # the worst robot
    assert ceddp.ingest_queue_dropped == 3
    assert (ceddp.ingest_nacks, ceddp.ingest_duplicates) == (5, 7)
    assert ceddp.cpu_us_per_sample == 1250.0  # 0.5 core x 10 s / 4000
    point = fleet_point(
        rows=rows,
        ceddps=[ceddp],
        topics=2,
        rate_hz=100,
        processes=2,
        window_s=10.0,
        workers_cpu_cores=1.0,
        host_busy_cores=1.6,
        host_steal_cores=0.25,
    )
    assert point.offered == 8000 and point.offered_per_s == 800
    assert point.sent == 4000 and point.sent_ratio == 0.5
    assert point.delivered_ratio == 0.5 and point.generator_limited
    assert point.latency_ms_p50 == pytest.approx(1.125)  # the median robot's p50
    assert point.latency_ms_p99 == 6.0
    assert point.latency_ms_p99_median_robot == 4.5  # robots' p99 3, 4, 5 and 6 ms
    assert point.ceddp_cpu_cores == 0.5 and point.ceddp_rss_mb == 120
    assert point.reconciled and point.failures == []
    text = format_run(point, [ceddp], rows)
    assert "reconciled: sent == delivered + lost for all 4 robots" in text
    assert "GENERATOR-LIMITED" in text
    assert "p99 (worst robot) 6.00 ms (median robot 4.50 ms)" in text
    assert "host busy 1.60 of" in text and "cores (stolen by the hypervisor 0.25)" in text
    assert point.steal_flagged and "STOLEN: the hypervisor took 0.25 cores (2.5 s" in text


@pytest.mark.parametrize(
    ("stolen", "flagged"), [(None, False), (0.0, False), (0.009, False), (0.01, True), (0.3, True)]
)
def test_a_run_is_flagged_when_the_hypervisor_took_a_hundredth_of_a_core(
    tmp_path: Path, stolen: float | None, flagged: bool
) -> None:
    rows = _rows(2)
    point = fleet_point(
        rows=rows,
        ceddps=[],
        topics=2,
        rate_hz=100,
        processes=1,
        window_s=60.0,
        workers_cpu_cores=1.0,
        host_busy_cores=1.8,
        host_steal_cores=stolen,
        host_steal_cores_peak=None if stolen is None else 4 * stolen,
    )
    assert point.steal_flagged is flagged
    text = format_run(point, [], rows)
    assert ("STOLEN" in text) is flagged
    if stolen is not None:
        assert f"(stolen by the hypervisor {stolen:.2f}, up to {4 * stolen:.2f} in one" in text
    if flagged:
        assert f"{stolen * 60:.1f} s of CPU over the window; up to {4 * stolen:.2f} cores" in text
    assert result_dict(point, [], rows)["fleet"]["steal_flagged"] is flagged
    path = tmp_path / "sweep.csv"
    write_sweep_csv(path, [point], [[]])
    assert _read_csv(path)[0]["steal_flagged"] == str(flagged)


def test_a_run_that_does_not_reconcile_prints_failed() -> None:
    rows = robot_rows({"c0-r001": (0, 0)}, [_summary({"c0-r001": _row(100, 90, 0)})], {})
    point = fleet_point(
        rows=rows,
        ceddps=[],
        topics=1,
        rate_hz=10,
        processes=1,
        window_s=10.0,
        workers_cpu_cores=0.1,
        host_busy_cores=None,
        failures=["worker0 exited with code 1"],
    )
    assert not point.reconciled
    assert point.failures[0] == "worker0 exited with code 1"
    text = format_run(point, [], rows)
    assert "FAILED: 2 problem(s):" in text and "(+10 unaccounted)" in text


def test_the_knee_is_the_first_n_past_either_bound() -> None:
    assert find_knee([(1, 1.0, 1.0), (5, 2.0, 1.0), (10, 3.0, 1.0)]) is None
    knee = find_knee([(10, 12.0, 1.0), (1, 1.0, 1.0), (5, 2.0, 1.0)])
    assert knee is not None and knee.robots == 10 and knee.reason == "p99 12.0 ms > 10 ms"
    knee = find_knee([(1, 1.0, 1.0), (5, 2.0, 0.98), (10, 30.0, 0.5)])
    assert knee is not None and knee.robots == 5
    assert knee.reason == "delivered/offered 0.980 < 0.99"
    assert over_the_knee(None, 1.0) == "nothing delivered"
    assert over_the_knee(15.0, 1.0, p99_bound_ms=20.0) is None
    assert over_the_knee(5.0, 0.9, min_ratio=0.8) is None


def _point(n: int, p99: float) -> tuple[Any, list[CeddpFigures]]:
    rows = _rows(n, p99)
    figures = [ceddp_figures(0, _summary({}), rows, _process(0.1 * n), 10.0)]
    point = fleet_point(
        rows=rows,
        ceddps=figures,
        topics=1,
        rate_hz=100,
        processes=1,
        window_s=10.0,
        workers_cpu_cores=0.2,
        host_busy_cores=1.0,
    )
    return point, figures


def test_knees_of_a_sweep_for_the_fleet_and_each_ceddp(tmp_path: Path) -> None:
    sweep = [_point(1, 1.0), _point(2, 3.0), _point(4, 9.0)]
    points = [p for p, _ in sweep]
    per_ceddp = [f for _, f in sweep]
    knee = fleet_knee(points)
    assert knee is not None and knee.robots == 4  # worst robot p99 = 9 + 4 = 13 ms
    assert ceddp_knees(points, per_ceddp) == {0: knee}
    assert fleet_knee(points, p99_bound_ms=20.0) is None
    path = tmp_path / "sweep.csv"
    write_sweep_csv(path, points, per_ceddp)
    lines = _read_csv(path)
    assert [int(line["robots"]) for line in lines] == [1, 2, 4]
    assert float(lines[2]["ceddp0_cpu_cores"]) == pytest.approx(0.4)


def test_robot_csv_and_json_have_every_robot(tmp_path: Path) -> None:
    rows = _rows(3)
    path = tmp_path / "robots.csv"
    write_robot_csv(path, rows)
    lines = _read_csv(path)
    assert [line["robot"] for line in lines] == ["c0-r001", "c0-r002", "c0-r003"]
    assert all(line["reconciled"] == "True" for line in lines)
    point, figures = _point(3, 1.0)
    doc = result_dict(point, figures, rows)
    assert len(doc["robots"]) == 3 and doc["robots"][0]["reconciled"] is True
    assert set(doc["unavailable"]) == {"ingest_backlog", "dashboard_dropped"}


def test_unavailable_names_dashboard_drops_only_when_a_ceddp_did_not_publish_them() -> None:
    rows = _rows(1)
    published = ceddp_figures(0, _summary({}), rows, None, 1.0, {"dashboard_dropped": 2})
    assert "dashboard_dropped" not in unavailable([published])
    silent = ceddp_figures(0, _summary({}), rows, None, 1.0, None)
    assert "dashboard_dropped" in unavailable([published, silent])


def test_the_ingest_backlog_comes_from_the_ceddp_s_reports_else_its_summary() -> None:
    rows = _rows(1)
    reported = ceddp_figures(0, _summary({}), rows, None, 1.0, {"backlog_ms_max": 12.5})
    assert reported.ingest_backlog_ms_max == 12.5
    idle = {**_summary({}), "ingest": {"backlog_ms_max": 40.0}}  # the window's 0 wins
    assert (
        ceddp_figures(0, idle, rows, None, 1.0, {"backlog_ms_max": 0.0}).ingest_backlog_ms_max == 0
    )
    assert "ingest_backlog" not in unavailable([reported])
    summary = {**_summary({}), "ingest": {"backlog_ms_max": 3, "backlog_ms_p99": 1.5}}
    from_summary = ceddp_figures(0, summary, rows, None, 1.0, None)
    assert (from_summary.ingest_backlog_ms_max, from_summary.ingest_backlog_ms_p99) == (3.0, 1.5)
    silent = ceddp_figures(0, _summary({}), rows, None, 1.0, None)
    assert silent.ingest_backlog_ms_max is None and silent.ingest_backlog_ms_p99 is None
    assert "ingest_backlog" in unavailable([reported, silent])


def test_the_time_in_the_ceddp_comes_from_its_summary() -> None:
    rows = _rows(1)
    ingest = {"sojourn_ms_p50": 0.8, "sojourn_ms_p99": 9.5, "sojourn_ms_max": 61.0}
    figures = ceddp_figures(0, {**_summary({}), "ingest": ingest}, rows, None, 1.0, None)
    assert (figures.sojourn_ms_p99, figures.sojourn_ms_max) == (9.5, 61.0)
    silent = ceddp_figures(0, _summary({}), rows, None, 1.0, None)
    assert silent.sojourn_ms_p99 is None and silent.sojourn_ms_max is None


def test_per_sample_cpu() -> None:
    assert per_sample_us(0.5, 10.0, 5000) == 1000.0
    assert per_sample_us(None, 10.0, 5000) is None
    assert per_sample_us(0.5, 10.0, 0) is None


def _read_csv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as fh:
        return list(csv.DictReader(fh))
