"""``benchmarks/links.py`` on one short cell: QUIC with mutual TLS at 5 % loss each way in the
kernel lab, its row of the table filled in and reconciled. Root only (tests/lab_support.py)."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.lab_support import require_lab

pytestmark = [pytest.mark.integration, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]


def test_links_benchmark_prints_a_filled_row_for_quic_at_5_pct(tmp_path: Path) -> None:
    require_lab()
    out = tmp_path / "links"
    started = time.monotonic()
    command = [sys.executable, str(ROOT / "benchmarks" / "links.py"), "--links", "quic"]
    done = subprocess.run(
        [*command, "--loss", "5", "--duration", "8", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=90,
        check=False,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert time.monotonic() - started < 30
    (row,) = json.loads((out / "links.json").read_text())["rows"]
    assert (row["link"], row["loss_pct"], row["status"]) == ("quic", 5.0, "ok"), row
    assert row["reconciled"] == "yes", row["not_reconciled"]
    for key in ("latency_ms_p50", "latency_ms_p99", "hello_ms_p99", "samples_per_s"):
        assert isinstance(row[key], float), (key, row)
    assert row["samples_received"] > 100 and row["hello_sent"] > 50, row
    assert row["wire_kb_per_s"] > 0 and row["robot_cpu_pct"] > 0 and row["ceddp_cpu_pct"] > 0
    # the progress lines name the cell, the table has its row and the CSV the same figures
    assert "[1/1 quic 5 %]" in done.stderr
    line = next(t for t in done.stdout.splitlines() if t.split()[:3] == ["quic", "5", "%"])
    assert line.split()[-1] == "yes", done.stdout
    assert "quic,5.0,ok" in (out / "links.csv").read_text()
