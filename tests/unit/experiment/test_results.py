"""results.csv rows from a CEDDP summary, resumability, and the report built from the CSV."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import pytest

from arpz.experiment.report import ReportError, consistency, write_report
from arpz.experiment.results import (
    COLUMNS,
    append_row,
    done_keys,
    error_row,
    read_rows,
    refresh_rows,
    row_from_summary,
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


def summary(*, opt: bool = False, mission: str | None = None) -> dict[str, Any]:
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
