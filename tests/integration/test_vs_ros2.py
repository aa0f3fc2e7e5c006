"""``benchmarks/vs_ros2.py`` as a contributor runs it: real rclpy nodes over Fast DDS, a real
Zenoh router and arpz's channel, each middleware's publisher and subscriber in processes of
their own; its table has every middleware's figures for every row, and the run exits 0. The lab
case (root only, tests/lab_support.py) runs the 10 % loss cells of one payload."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from tests.lab_support import require_lab

pytestmark = [pytest.mark.integration, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
BENCHMARK = ROOT / "benchmarks" / "vs_ros2.py"
MIDDLEWARES = ("arpz", "rclpy", "zenoh")
CPU_ROWS = (
    ("publisher", "cpu_pub_us"),
    ("subscriber", "cpu_sub_us"),
    ("all processes", "cpu_all_us"),
)


def run_benchmark(tmp_path: Path, *args: str) -> tuple[subprocess.CompletedProcess[str], Any]:
    pytest.importorskip("rclpy", reason="ROS 2's wheels: pip install 'arpz[ros2]'")
    out = tmp_path / "vs_ros2.json"
    started = time.monotonic()
    done = subprocess.run(
        [sys.executable, str(BENCHMARK), "--quick", *args, "--json", str(out)],
        capture_output=True,
        text=True,
        timeout=150,
        check=False,
        cwd=tmp_path,
    )
    print(f"{' '.join(args)}: {time.monotonic() - started:.1f} s")
    assert done.returncode == 0, done.stdout + done.stderr[-3000:]
    return done, json.loads(out.read_text())


def by_metric(rows: list[dict[str, Any]], qos: str) -> dict[str, dict[str, Any]]:
    return {row["metric"]: row for row in rows if row["qos"] == qos}


def test_quick_loopback_run_prints_every_middleware_for_every_row(tmp_path: Path) -> None:
    # one QoS keeps the test short (KEEP_LAST runs the same code paths; the full run has both)
    done, doc = run_benchmark(tmp_path, "--skip-lab", "--sizes", "24", "--qos", "keep_all")
    assert doc["failures"] == []
    table = [line for line in done.stdout.splitlines() if line.startswith("| 24 B |")]
    # throughput, 3 CPU rows, 2 round trips, lost and one-way at 0 %
    assert len(table) == 8, done.stdout
    for line in table:
        cells = [cell.strip() for cell in line.strip("|").split("|")]
        assert len(cells) == 9 and "-" not in cells[3:6], line  # every middleware measured
        assert cells[8] in ("yes", "no", "tie", "mixed"), line
    for qos in ("keep_all",):
        rows = by_metric(doc["rows"], qos)
        assert len(rows) == 8, rows.keys()
        for mw in MIDDLEWARES:
            throughput = rows["throughput, msg/s (MB/s)"]["figures"][mw]
            assert throughput["msg_s"] > 100, (qos, mw, throughput)
            assert throughput["mb_s"] == pytest.approx(throughput["msg_s"] * 24 / 1e6)
            for who, key in CPU_ROWS:
                assert rows[f"CPU us/msg, {who}"]["figures"][mw][key] > 0, (who, mw)
            for rate in ("100", "1000"):
                rtt = rows[f"round trip {rate} Hz, p50 / p99 ms"]["figures"][mw]
                assert 0 < rtt["p50_us"] <= rtt["p99_us"] < 1e6, (rate, mw, rtt)
            stream = rows["one-way p50 / p99 ms, 0 % loss"]["figures"][mw]
            assert 0 < stream["p50_ms"] <= stream["p99_ms"], (mw, stream)
        # RELIABLE KEEP_ALL on loopback: every message of the paced stream arrives
        if qos == "keep_all":
            lost = rows["lost, 0 % loss (loopback)"]["figures"]
            assert all(lost[mw]["lost_pct"] == 0 for mw in MIDDLEWARES), lost
        assert rows["throughput, msg/s (MB/s)"]["arpz/rclpy"].endswith("x")
        assert rows["throughput, msg/s (MB/s)"]["arpz/zenoh"].endswith("x")
    # one progress line a cell, as it is measured
    progress = [line for line in done.stderr.splitlines() if line.startswith("[")]
    assert len(progress) == 12 and progress[-1].startswith("[12/12 "), done.stderr
    assert "rclpy" in done.stdout and "Fast DDS" in done.stdout


def test_quick_lab_run_at_10_pct_loss(tmp_path: Path) -> None:
    require_lab()
    done, doc = run_benchmark(
        tmp_path, "--lab-only", "--losses", "10", "--sizes", "24", "--qos", "keep_all"
    )
    rows = by_metric(doc["rows"], "keep_all")
    assert sorted(rows) == ["lost, 10 % loss (lab)", "one-way p50 / p99 ms, 10 % loss"]
    lost = {mw: rows["lost, 10 % loss (lab)"]["figures"][mw]["lost_pct"] for mw in MIDDLEWARES}
    # arpz's channel recovers what the link loses; raw Zenoh over UDP does not (300 samples
    # at 10 % each way: none lost would be a link that lost nothing)
    assert lost["arpz"] == 0 and lost["zenoh"] > 0, lost
    assert 0 <= lost["rclpy"] <= 100, lost
    one_way = rows["one-way p50 / p99 ms, 10 % loss"]["figures"]["arpz"]
    assert 0 < one_way["p50_ms"] <= one_way["p99_ms"] < 1000, one_way
    assert "lab link udp" in done.stdout
