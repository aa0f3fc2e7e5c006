"""results.csv rows from a CEDDP summary, resumability, and the report built from the CSV."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import msgspec
import pytest

from arpz.experiment.report import (
    METRICS,
    ReportError,
    _bar_panel,
    _grouped,
    consistency,
    wilson,
    write_report,
)
from arpz.experiment.results import (
    COLUMNS,
    append_row,
    done_keys,
    error_row,
    read_rows,
    refresh_rows,
    row_from_summary,
    upgrade_header,
)
from arpz.experiment.spec import OPT_DEPTH, Cell


def _robot(produced: int, held: int, lost: int, **extra: Any) -> dict[str, Any]:
    sent = produced - held
    return {
        "produced": produced,
        "sent": sent,
        "held_back": held,
        "write_failures": 0,
        "received": sent - lost,
        "lost": lost,
        "cc_discarded": 3,
        "retransmitted": 7,
        "latency_ms_p50": 5.0,
        "latency_ms_p99": 9.0,
        "topics": {"imu": {"overwritten_unacked": 2}},
        "final_stats": True,
        **extra,
    }


def _staleness_and_downlink(robot: str, data: dict[str, Any], index: int) -> None:
    """The fields of an issue-14 CEDDP: staleness, cache forgets, downlink, watchdog."""
    data["staleness_ms_p99"] = 40.0 + 10 * index  # pooled over the robot's sensor topics
    data["topics"] = {
        "imu": {
            "overwritten_unacked": 2,
            "staleness_ms_p50": 3.0 + index,
            "staleness_ms_p99": 30.0,
            "staleness_ms_max": 90.0 + index,
            "cache_forgets": 1,
        },
        "light": {
            "overwritten_unacked": 0,
            "staleness_ms_p50": 10.0 + index,
            "staleness_ms_p99": 35.0,
            "staleness_ms_max": 60.0,
            "cache_forgets": 0,
        },
        # the Hello probe is not a sensor: its staleness must not count
        "hello": {"staleness_ms_p50": 999.0, "staleness_ms_p99": 999.0, "staleness_ms_max": 999.0},
    }
    hello_hops = 0 if robot == "robot2" else 40
    data["downlink"] = {
        "hello": {
            "written": hello_hops,
            "unmatched": 0,
            "write_failures": 0,
            "delivered": hello_hops - 2 if hello_hops else 0,
            "lost": 1 if hello_hops else 0,
            "lifespan_expired": 1 if hello_hops else 0,
            # robot2 gets no Hello hops: nothing to reconcile
            "reconciled": True if hello_hops else None,
        },
        "velocity": {
            "written": 100,
            "unmatched": 5,
            "write_failures": 0,
            "delivered": 94,
            "lost": 1,
            "lifespan_expired": 0,
            "reconciled": True,
        },
    }
    data["commands_expired"] = 1 if hello_hops else 0
    data["watchdog_stops"] = {"velocity": index}
    data["incompatible_qos"] = []
    data["refused"] = 0


def summary(
    *, opt: bool = False, mission: str | None = None, issue14: bool = False
) -> dict[str, Any]:
    hello = {"sent": 50, "received": 45, "lost": 5, "rtt_ms_p50": 20.0, "rtt_ms_p99": 80.0}
    out: dict[str, Any] = {
        "robots": {
            "robot1": _robot(1000, 100, 10, hello=hello),
            "robot2": _robot(800, 0, 0, latency_ms_p50=7.0),
            "robot3": _robot(800, 0, 0),
        },
        "qos": None,
        "mission": None,
    }
    if opt:
        qos = {"rate_hz": 14.0, "deadline_s": 1 / 14, "depth": 699}
        robots = dict.fromkeys(out["robots"], qos)
        fewer = {"robot3": {"rate_hz": 15.7, "deadline_s": 1 / 15.7, "depth": 782}}
        out["qos"] = {
            # epoch 3: robots left at shutdown; epoch 2 was in force while all three ran
            "assignments": [
                {"epoch": 1, "robots": robots},
                {"epoch": 2, "robots": robots},
                {"epoch": 3, "robots": fewer},
            ],
            "acks": {
                "robot1": {"status": "applied", "epoch": 2},
                "robot2": {"status": "applied", "epoch": 2},
                "robot3": {"status": "applied", "epoch": 3},
            },
        }
    if mission:
        out["mission"] = {"result": {"mission": mission, "reason": "why", "duration_s": 33.0}}
    if issue14:
        for index, (robot, data) in enumerate(out["robots"].items()):
            _staleness_and_downlink(robot, data, index)
    return out


def test_row_from_summary_sums_and_percentages() -> None:
    cell = Cell(100.0, 10, "lc", 1, "wifi-bad")
    row = row_from_summary(
        cell,
        summary(),
        experiment="e",
        link={"received": 1000, "dropped": 80},
        measured_s=5.0,
        wall_s=12.0,
        rrd="rrd/x.rrd",
    )
    assert row["samples_produced"] == 2600 and row["samples_held_back"] == 100
    assert row["samples_sent"] == 2500 and row["samples_lost"] == 10
    assert row["sample_loss_pct"] == pytest.approx(0.4)
    assert row["loss_pct"] == pytest.approx(10.0) and row["latency_ms_p50"] == 20.0
    assert row["sample_latency_ms_p50"] == 7.0  # the worst robot
    assert row["samples_discarded"] == 9 and row["samples_overwritten_unacked"] == 6
    assert (row["rate_hz"], row["qos_depth"], row["deadline_ms"]) == (100.0, 10, 10.0)
    assert row["link_loss_pct"] == pytest.approx(8.0)
    assert row["mission"] is None and row["final_reports"] == 3
    assert set(row) <= set(COLUMNS)
    # a CEDDP from before staleness and the reliable downlink: unknown, not zero
    for column in (
        "staleness_ms_p50",
        "staleness_ms_p99",
        "staleness_ms_max",
        "cache_forgets",
        "hello_hops_written",
        "commands_delivered",
        "commands_expired",
        "downlink_reconciled",
        "watchdog_stops",
        "incompatible_qos",
    ):
        assert row[column] is None, column


def _row(cell: Cell, data: dict[str, Any], **kwargs: Any) -> dict[str, Any]:
    return row_from_summary(
        cell, data, experiment="e", link={}, measured_s=1, wall_s=1, rrd="", **kwargs
    )


def test_row_staleness_over_sensor_topics() -> None:
    row = _row(Cell(100.0, 10, "lc", 1, "wifi-bad"), summary(issue14=True))
    # max: over every sensor topic (not Hello); p99: the worst robot's pooled p99; p50: the
    # median of the six per-topic p50s (3, 4, 5, 10, 11, 12)
    assert row["staleness_ms_max"] == 92.0
    assert row["staleness_ms_p99"] == 60.0
    assert row["staleness_ms_p50"] == pytest.approx(7.5)
    assert row["cache_forgets"] == 3


def test_row_staleness_p99_falls_back_to_the_topics() -> None:
    data = summary(issue14=True)
    for robot in data["robots"].values():
        robot["staleness_ms_p99"] = None  # no pooled figure: the worst topic's p99
    assert _row(Cell(100.0, 10, "lc", 1, "lan"), data)["staleness_ms_p99"] == 35.0


def test_row_downlink_reconciliation() -> None:
    data = summary(issue14=True)
    row = _row(Cell(100.0, 10, "lc", 1, "lan"), data)
    assert (row["hello_hops_written"], row["hello_hops_delivered"], row["hello_hops_lost"]) == (
        80,
        76,
        2,
    )
    assert (row["commands_written"], row["commands_delivered"], row["commands_lost"]) == (
        300,
        282,
        3,
    )
    assert row["commands_expired"] == 2 and row["watchdog_stops"] == 3
    assert row["downlink_reconciled"] == "yes" and row["downlink_unreconciled"] == ""
    assert row["incompatible_qos"] == 0 and row["samples_refused"] == 0
    # a robot whose final report never came: its keys that reached it cannot reconcile
    data["robots"]["robot3"]["downlink"]["velocity"]["reconciled"] = None
    data["robots"]["robot1"]["downlink"]["hello"]["reconciled"] = False
    row = _row(Cell(100.0, 10, "lc", 1, "lan"), data)
    assert row["downlink_reconciled"] == "no"
    assert row["downlink_unreconciled"] == "robot1/hello;robot3/velocity"
    # plain puts (plain_downlink): no channel, so nothing to reconcile, and said so
    for robot in data["robots"].values():
        for c in robot["downlink"].values():
            c["channel"], c["reconciled"] = False, None
    row = _row(Cell(100.0, 10, "lc", 1, "lan"), data)
    assert row["downlink_reconciled"] == "plain" and row["downlink_unreconciled"] == ""
    assert row["commands_written"] == 300  # still counted


def test_row_records_the_configured_qos_of_optr_and_optd() -> None:
    """Without a CEDDP assignment the QoS used is the one the robots were configured with."""
    row = _row(Cell(100.0, 5, "optr", 1, "lan"), summary(), configured=(14.8, 5))
    assert (row["rate_hz"], row["qos_depth"]) == (14.8, 5)
    assert row["deadline_ms"] == pytest.approx(1000 / 14.8)
    row = _row(Cell(100.0, OPT_DEPTH, "optd", 1, "lan"), summary(), configured=(100.0, 738))
    assert (row["rate_hz"], row["qos_depth"], row["qos_epochs"]) == (100.0, 738, 0)


def test_row_takes_the_qos_actually_assigned() -> None:
    cell = Cell(100.0, OPT_DEPTH, "opt", 1, "lan")
    row = row_from_summary(
        cell, summary(opt=True), experiment="e", link={}, measured_s=1, wall_s=1, rrd=""
    )
    assert (row["rate_hz"], row["qos_depth"]) == (14.0, 699)
    assert row["qos_epochs"] == 3 and row["qos_applied"] == 3


def test_mission_without_verdict_is_a_failure() -> None:
    cell = Cell(100.0, 1, "baseline", 1, "lan")
    data = summary()
    data["mission"] = {"result": None}
    row = row_from_summary(cell, data, experiment="e", link={}, measured_s=1, wall_s=1, rrd="")
    assert row["mission"] == "failure" and "never started" in row["mission_reason"]


def _write(path: Path, cells: list[Cell], **kwargs: Any) -> None:
    for cell in cells:
        row = row_from_summary(
            cell, summary(**kwargs), experiment="e", link={}, measured_s=1, wall_s=2, rrd=""
        )
        append_row(path, row)


def test_resume_skips_finished_cells_and_retries_errors(tmp_path: Path) -> None:
    path = tmp_path / "results.csv"
    ok, failed = Cell(100.0, 1, "baseline", 1, "lan"), Cell(100.0, 5, "baseline", 1, "lan")
    _write(path, [ok])
    append_row(path, error_row(failed, experiment="e", error="boom\nline", wall_s=1.0))
    assert done_keys(path) == {ok.key}
    # a partial last line (a crash mid-write) is ignored, not misread
    with path.open("a", encoding="utf-8") as handle:
        handle.write("e,100,10,baseline")
    assert len(read_rows(path)) == 2
    with path.open(encoding="utf-8") as handle:
        header = next(csv.reader(handle))
    assert tuple(header) == COLUMNS


def test_retried_cell_replaces_its_error(tmp_path: Path) -> None:
    path = tmp_path / "results.csv"
    cell = Cell(200.0, 1, "lc", 1, "lan")
    append_row(path, error_row(cell, experiment="e", error="x", wall_s=1.0))
    _write(path, [cell])
    rows = read_rows(path)
    assert [r["status"] for r in rows] == ["ok"]


def test_report_writes_figures_and_markdown(tmp_path: Path) -> None:
    path = tmp_path / "results.csv"
    cells = [
        Cell(rate, depth, config, 1, "wifi-bad")
        for rate in (100.0, 1000.0)
        for depth, config in ((1, "baseline"), (100, "baseline"), (1, "lc"), (OPT_DEPTH, "opt"))
    ]
    _write(path, cells, mission="success")
    paths = write_report(tmp_path)
    assert paths[0].name == "REPORT.md"
    names = {p.name for p in paths[1:]}
    for metric in ("latency", "loss", "sample_loss", "mission"):
        assert f"experiment_{metric}.png" in names
        assert f"experiment_{metric}_r100.png" in names
    assert all(p.stat().st_size > 1000 for p in paths[1:])
    text = paths[0].read_text(encoding="utf-8")
    assert "## Rmax = 1000 Hz, network wifi-bad" in text and "Opt(D)" in text
    assert "Every ok row reconciles" in text


def test_consistency_flags_counts_that_do_not_add_up(tmp_path: Path) -> None:
    path = tmp_path / "results.csv"
    _write(path, [Cell(100.0, 1, "baseline", 1, "lan")])
    rows = read_rows(path)
    assert consistency(rows) == []
    rows[0]["samples_lost"] = "11"
    assert any("sent != received + lost" in p for p in consistency(rows))
    _write(path, [Cell(200.0, 1, "baseline", 1, "lan")])
    rows = read_rows(path)
    rows[1]["final_reports"] = "2"
    assert any("final counters never reached" in p for p in consistency(rows))


def test_report_without_results(tmp_path: Path) -> None:
    with pytest.raises(ReportError, match="no results"):
        write_report(tmp_path)


def test_refresh_rederives_rows_from_kept_summaries(tmp_path: Path) -> None:
    path = tmp_path / "results.csv"
    cell = Cell(100.0, OPT_DEPTH, "opt", 1, "lan")
    data = summary(opt=True)
    row = row_from_summary(
        cell, data, experiment="e", link={"received": 10}, measured_s=1, wall_s=2, rrd="r"
    )
    row["rate_hz"] = 99.0  # as an older version computed it
    append_row(path, row)
    append_row(path, error_row(Cell(100.0, 1, "lc", 1, "lan"), experiment="e", error="x", wall_s=1))
    (tmp_path / "runs" / cell.slug).mkdir(parents=True)
    (tmp_path / "runs" / cell.slug / "summary.json").write_text(json.dumps(data), encoding="utf-8")
    assert refresh_rows(tmp_path) == 1
    rows = read_rows(path)
    assert [r["status"] for r in rows] == ["ok", "error"]
    assert rows[0]["rate_hz"] == "14" and rows[0]["link_datagrams"] == "10"


#: the columns of results.csv before issue 14 (staleness, downlink, watchdog)
OLD_COLUMNS = COLUMNS[: COLUMNS.index("staleness_ms_p50")] + COLUMNS[COLUMNS.index("mission") :]


def _old_csv(path: Path, cells: list[Cell]) -> None:
    """A results.csv as an older version wrote it: fewer columns."""
    with path.open("w", encoding="utf-8", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=OLD_COLUMNS, extrasaction="ignore")
        writer.writeheader()
        for cell in cells:
            row = _row(cell, summary(mission="success"))
            writer.writerow({k: "" if v is None else v for k, v in row.items()})


def test_an_older_results_csv_reads_and_reports(tmp_path: Path) -> None:
    path = tmp_path / "results.csv"
    _old_csv(path, [Cell(100.0, 1, "baseline", r, "lan") for r in (1, 2)])
    rows = read_rows(path)
    assert len(rows) == 2
    assert all(r["staleness_ms_p99"] == "" and r["downlink_reconciled"] == "" for r in rows)
    assert consistency(rows) == []
    paths = write_report(tmp_path)
    names = {p.name for p in paths}
    assert "experiment_latency.png" in names
    assert "experiment_staleness.png" not in names  # no staleness in an older file


def test_resuming_an_older_results_csv_upgrades_its_header(tmp_path: Path) -> None:
    path = tmp_path / "results.csv"
    old = Cell(100.0, 1, "baseline", 1, "lan")
    _old_csv(path, [old])
    new = Cell(100.0, 5, "baseline", 1, "lan")
    append_row(path, _row(new, summary(issue14=True)))
    with path.open(encoding="utf-8") as handle:
        assert tuple(next(csv.reader(handle))) == COLUMNS
    rows = {r["depth"]: r for r in read_rows(path)}
    assert done_keys(path) == {old.key, new.key}
    assert rows["1"]["staleness_ms_p99"] == "" and rows["1"]["hello_sent"] == "50"
    assert rows["5"]["staleness_ms_p99"] == "60" and rows["5"]["downlink_reconciled"] == "yes"
    assert upgrade_header(path) is False  # already today's columns


def _repeats(tmp_path: Path) -> list[dict[str, str]]:
    """Three repeats of one cell whose Hello latency is 10, 20 and 60 ms."""
    path = tmp_path / "results.csv"
    cell = [Cell(100.0, 1, "baseline", r, "wifi-bad") for r in (1, 2, 3)]
    runs = zip(cell, (10.0, 20.0, 60.0), ("success", "failure", "success"), strict=True)
    for c, latency, verdict in runs:
        data = summary(mission=verdict, issue14=True)
        data["robots"]["robot1"]["hello"]["rtt_ms_p50"] = latency
        append_row(path, _row(c, data))
    return read_rows(path)


def test_spread_is_min_max_over_repeats(tmp_path: Path) -> None:
    rows = _repeats(tmp_path)
    latency = next(m for m in METRICS if m.key == "latency")
    spread = latency.spread(rows)
    assert spread is not None
    assert (spread.value, spread.low, spread.high, spread.n) == (30.0, 10.0, 60.0, 3)
    assert sorted(spread.points) == [10.0, 20.0, 60.0]
    mission = next(m for m in METRICS if m.key == "mission").spread(rows)
    assert mission is not None and mission.value == pytest.approx(200 / 3)
    low, high = wilson(2, 3)
    assert (mission.low, mission.high) == (pytest.approx(100 * low), pytest.approx(100 * high))
    assert 0 < low < 2 / 3 < high < 1
    assert wilson(0, 3)[0] == 0 and wilson(3, 3)[1] == 1


def test_bars_carry_the_spread_as_whiskers(tmp_path: Path) -> None:
    import matplotlib.pyplot as plt
    from matplotlib.container import BarContainer

    rows = _repeats(tmp_path)
    latency = next(m for m in METRICS if m.key == "latency")
    fig, ax = plt.subplots()
    try:
        groups = _grouped(rows)
        assert _bar_panel(ax, latency, groups, "wifi-bad", "100", ["baseline"], ["1"])
        bars = [c for c in ax.containers if isinstance(c, BarContainer)]
        assert len(bars) == 1 and bars[0].patches[0].get_height() == 30.0
        assert bars[0].errorbar is not None
        (segment,) = bars[0].errorbar.lines[2][0].get_segments()
        assert [float(y) for _, y in segment] == [10.0, 60.0]  # the whisker: min to max
        # one dot per repeat
        dots = [c for c in ax.collections if c.get_offsets().shape == (3, 2)]
        assert len(dots) == 1 and sorted(dots[0].get_offsets()[:, 1]) == [10.0, 20.0, 60.0]
    finally:
        plt.close(fig)


def test_report_has_staleness_and_ranges(tmp_path: Path) -> None:
    _repeats(tmp_path)
    paths = write_report(tmp_path)
    names = {p.name for p in paths}
    assert {"experiment_staleness.png", "experiment_staleness_r100.png"} <= names
    text = paths[0].read_text(encoding="utf-8")
    assert "30 [10-60] ms" in text and "staleness 60 ms" in text and "(2/3)" in text


def test_report_from_a_committed_csv_elsewhere(tmp_path: Path) -> None:
    committed = tmp_path / "results" / "paper-machines"
    committed.mkdir(parents=True)
    _repeats(committed)
    out = tmp_path / "regenerated"
    paths = write_report(committed / "results.csv", out=out)
    assert paths[0] == out / "REPORT.md"
    assert all(p.is_relative_to(out) for p in paths)
    assert "](figures/experiment_latency.png)" in paths[0].read_text(encoding="utf-8")
    assert sorted(p.name for p in committed.iterdir()) == ["results.csv"]  # left as committed


def test_consistency_flags_an_unreconciled_downlink(tmp_path: Path) -> None:
    path = tmp_path / "results.csv"
    data = summary(issue14=True)
    data["robots"]["robot3"]["downlink"]["velocity"]["reconciled"] = False
    append_row(path, _row(Cell(100.0, 1, "baseline", 1, "lan"), data))
    assert any(
        "downlink not reconciled (robot3/velocity)" in p for p in consistency(read_rows(path))
    )


def test_refresh_takes_optr_and_optd_qos_from_the_saved_spec(tmp_path: Path) -> None:
    from arpz.experiment.fleet import configured_qos
    from arpz.experiment.presets import paper_machines

    spec = paper_machines()
    (tmp_path / "spec.json").write_bytes(msgspec.json.encode(spec))
    path = tmp_path / "results.csv"
    cell = Cell(100.0, OPT_DEPTH, "optd", 1, "wifi-bad")
    append_row(path, _row(cell, summary()))  # as an older version wrote it: Rmax, depth 0
    (tmp_path / "runs" / cell.slug).mkdir(parents=True)
    data = json.dumps(summary(issue14=True))
    (tmp_path / "runs" / cell.slug / "summary.json").write_text(data, encoding="utf-8")
    assert refresh_rows(tmp_path) == 1
    (row,) = read_rows(path)
    rate, depth = configured_qos(spec, cell)
    assert (float(row["rate_hz"]), int(row["qos_depth"])) == (rate, depth) == (100.0, 738)
    assert row["staleness_ms_p99"] == "60"
