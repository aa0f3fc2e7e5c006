"""Clock offsets through a real router: a robot whose clock is 0.5 s ahead on purpose
(``[clock] shift_s``) is measured, flagged, and its latencies corrected to its neighbour's."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from tests.integration.fleet import ceddp, robots, write_robot
from tests.support import wait_until

pytestmark = pytest.mark.integration

SHIFT_S = 0.5


def _summary(tmp: Path) -> dict[str, Any]:
    try:
        summary: dict[str, Any] = json.loads((tmp / "summary.json").read_text())
    except FileNotFoundError:
        return {}
    return summary


def _measured(tmp: Path) -> bool:
    rows = _summary(tmp).get("robots", {})
    return all(
        rows.get(robot, {}).get("clock", {}).get("offset_ms") is not None
        and rows[robot]["received"] > 100
        for robot in ("steady", "shifted")
    )


def test_a_shifted_robot_is_measured_flagged_and_its_latency_corrected(tmp_path: Path) -> None:
    extra = "summary_period_s = 0.2\n[clock]\nmax_offset_ms = 50\n"
    with ceddp(tmp_path, extra=extra) as (server, endpoint):
        configs = [
            write_robot(tmp_path, "steady", endpoint, preset="machine1"),
            write_robot(
                tmp_path,
                "shifted",
                endpoint,
                preset="machine1",
                extra=f"[clock]\nperiod_s = 0.5\nshift_s = {SHIFT_S}\n",
            ),
        ]
        with robots(tmp_path, configs) as procs:
            wait_until(lambda: _measured(tmp_path), timeout_s=15, what="both robots' offsets")
            for proc in procs:
                assert proc.interrupt() == 0, proc.output()
        assert server.interrupt() == 0, server.output()
    summary = _summary(tmp_path)
    steady, shifted = summary["robots"]["steady"], summary["robots"]["shifted"]
    print(
        f"offsets: steady {steady['clock']['offset_ms']} ms (delay {steady['clock']['delay_ms']}"
        f" ms), shifted {shifted['clock']['offset_ms']} ms (delay "
        f"{shifted['clock']['delay_ms']} ms); latency p50 steady {steady['latency_ms_p50']:.3f}"
        f" ms, shifted {shifted['latency_ms_p50']:.3f} ms (corrected)"
    )
    # the CEDDP's clock minus the robot's: the same host, so -shift, within a few ms
    assert abs(shifted["clock"]["offset_ms"] + SHIFT_S * 1e3) < 5
    assert abs(steady["clock"]["offset_ms"]) < 5
    assert shifted["clock"]["over_bound"] and not steady["clock"]["over_bound"]
    assert summary["clock"]["flagged"] == ["shifted"]
    flags = [e for e in summary["events"] if "clock offset" in e]
    assert len(flags) == 1 and "robot shifted: clock offset -" in flags[0], flags
    assert "exceeds 50 ms" in flags[0]
    # corrected: the shifted robot's latency is its neighbour's, not 500 ms off
    assert steady["clock_corrected"] and shifted["clock_corrected"]
    assert abs(shifted["latency_ms_p50"] - steady["latency_ms_p50"]) < 20
    assert shifted["latency_ms_p50"] > -5
    # the first estimate travels in the announcement, before the first reading
    assert shifted["clock"]["uncorrected_samples"] <= shifted["received"] * 0.02
    assert shifted["versions"]["arpz"] and shifted["versions"]["zenoh"]
