"""The dashboard's metric series, read back from the ``.rrd`` by Rerun's own reader: every value
at its stamp on its entity path, whatever the series' lengths (the flush sends slices of arrays
shared by all series, so an offset off by one would move values between series)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import pytest
from rerun.chunk import RrdReader

from arpz.ceddp.dashboard import Dashboard
from arpz.core.frames import TIMELINE, MetricsFrame
from tests.support import wait_until

T0_NS = 1_700_000_000_000_000_000


def series(rrd: Path) -> dict[str, list[tuple[int, float]]]:
    """entity path -> [(stamp_ns, value)] of every metric row in the file."""
    out: dict[str, list[tuple[int, float]]] = {}
    chunks = RrdReader(str(rrd)).stream().filter(content="/metrics/**", is_static=False)
    for chunk in chunks.to_chunks():
        batch = chunk.to_record_batch()
        stamps = batch.column(TIMELINE).cast("int64").to_pylist()
        values = batch.column("Scalars:scalars").to_pylist()
        rows = out.setdefault(str(chunk.entity_path), [])
        rows.extend((stamp, value[0]) for stamp, value in zip(stamps, values, strict=True))
    return {path: sorted(rows) for path, rows in out.items()}


def test_every_value_reaches_its_own_series_at_its_stamp(tmp_path: Path) -> None:
    rrd = tmp_path / "ceddp.rrd"
    dashboard = Dashboard(rrd, flush_period_s=3600)  # one flush, at close: all series at once
    expected: dict[str, list[tuple[int, float]]] = {}
    for tick in range(5):
        stamp_ns = T0_NS + tick * 500_000_000
        topics: dict[tuple[str, str], dict[str, float]] = {}
        # series of different lengths: robot2's imu joins at tick 2, robot1's pir leaves at 3
        for robot, topic in (("robot1", "lidar"), ("robot1", "pir"), ("robot2", "imu")):
            if (topic == "imu" and tick < 2) or (topic == "pir" and tick >= 3):
                continue
            rate = 100.0 * tick + len(topic) + (robot == "robot2")
            topics[(robot, topic)] = {"rate_hz": rate, "lost": float(tick)}
            for name, value in topics[(robot, topic)].items():
                path = f"/metrics/{name}/{robot}/{topic}"
                expected.setdefault(path, []).append((stamp_ns, value))
        robots = {"robot1": {"cpu_percent": 10.0 + tick}}
        expected.setdefault("/metrics/cpu_percent/robot1", []).append((stamp_ns, 10.0 + tick))
        assert dashboard.submit(MetricsFrame(stamp_ns, topics=topics, robots=robots))
    dashboard.close()
    assert dashboard.logged_rows == sum(len(rows) for rows in expected.values())
    assert series(rrd) == expected


def test_a_bad_value_is_logged_and_the_dashboard_goes_on(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    rrd = tmp_path / "ceddp.rrd"
    dashboard = Dashboard(rrd, flush_period_s=3600)
    bad: dict[str, Any] = {"rate_hz": None, "cpu_percent": 7.0}  # the good one after the bad
    dashboard.submit(MetricsFrame(T0_NS, robots={"robot1": bad}))
    dashboard.submit(MetricsFrame(T0_NS + 10**9, robots={"robot1": {"rate_hz": 5.0}}))
    dashboard.close()
    assert "/metrics/rate_hz/robot1 is not a number" in caplog.text
    assert dashboard.rows_refused == 1
    assert series(rrd) == {
        "/metrics/rate_hz/robot1": [(T0_NS + 10**9, 5.0)],
        "/metrics/cpu_percent/robot1": [(T0_NS, 7.0)],
    }


def test_the_first_flush_comes_half_a_period_after_start(tmp_path: Path) -> None:
    """Half a period out of phase with the summary the CEDDP persists every period from its
    start, and on time even when no frame arrives to wake the dashboard's thread."""
    started = time.monotonic()
    dashboard = Dashboard(tmp_path / "ceddp.rrd", flush_period_s=4.0)
    try:
        dashboard.submit(MetricsFrame(T0_NS, robots={"robot1": {"cpu_percent": 1.0}}))
        wait_until(lambda: dashboard.logged_rows == 1, timeout_s=10, what="the first flush")
        took = time.monotonic() - started
    finally:
        dashboard.close()
    assert 1.5 <= took < 3.5, took  # half of 4 s, not the whole period
