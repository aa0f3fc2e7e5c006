"""An experiment cell on a kernel link: ``networks = ["lab:PROFILE"]`` runs the cell's CEDDP and
robots in the lab's namespaces (arpz.lab), the profile applied by nftables to each robot's real
link, over QUIC with the fleet's mutual TLS (issue 39). Root only (tests/lab_support.py)."""

from __future__ import annotations

from pathlib import Path

import pytest

from arpz.experiment.runner import run_cell
from arpz.experiment.spec import ExperimentSpec
from tests.lab_support import require_lab

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def test_a_lab_cell_runs_the_fleet_over_a_lossy_kernel_link(tmp_path: Path) -> None:
    require_lab()
    spec = ExperimentSpec(
        name="lab-cell",
        rmax_hz=[50.0],
        depths=[100],
        configs=["baseline"],
        networks=["lab:loss-10"],
        lab_link="quic",
        presets=["machine1", "machine3"],
        hello_relay="robot2",
        duration_s=8.0,
    )
    (cell,) = spec.cells()
    row = run_cell(spec, cell, tmp_path)
    assert row["status"] == "ok", row["error"]
    # the kernel dropped about a tenth of the frames each way, counted by nftables
    assert int(row["link_datagrams"]) > 1000, row
    assert 5.0 < float(row["link_loss_pct"]) < 15.0, row
    assert int(row["samples_sent"]) > 0 and int(row["final_reports"]) == 2, row
    assert row["downlink_reconciled"] == "yes", row["downlink_unreconciled"]
    timeline = (tmp_path / "runs" / cell.slug / "lab_timeline.jsonl").read_text()
    assert "loss" in timeline
