"""Graceful overload through a real router: a fleet offered several times what the CEDDP can
ingest.

The CEDDP is given a known, small capacity (``[overload] planner_cost_us``: every reading cache
control passes costs the planner 10 ms of CPU, so a few hundred samples/s at most, depending on
how many repeat), and the QoS optimiser's Rmax lets two robots of six sensors each send about
300 Hz per sensor (3 600 samples/s). The CEDDP must notice (its ingest thread never waits,
latency climbs), cut the fleet's budget to what it measured it can take, assign lower rates, and
then stay within its latency bound, and every count must reconcile at the end.
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import pytest

from arpz.core.messages import (
    CEDDP_STATS_DECODER,
    QOS_ASSIGNMENT_DECODER,
    CeddpStats,
    QosAssignmentMsg,
)
from tests.integration.fleet import ceddp, robots
from tests.support import client, wait_until

# heavy or timing-bound: runs with the cores to itself (tests/conftest.py, cpu_share), the unit
# tests included: how fast the CEDDP drains its backlog after the cut depends on the host. Stop
# 28 saw it miss its 10 s in three full runs (two with a change since reverted, one of them with
# this marking) and pass alone in every run (13-18 s)
pytestmark = [pytest.mark.integration, pytest.mark.cpu_exclusive(whole_machine=True)]

LATENCY_BOUND_MS = 250.0
CEDDP = (
    "[qos]\nenabled = true\nrmax_hz = 2100.0\n"  # T = 7 (6 sensors + velocity): R = 299 Hz
    f"[overload]\nplanner_cost_us = 10000.0\nlatency_bound_ms = {LATENCY_BOUND_MS}\n"
)
#: after the budget is cut, the backlog drains within this (or 10x its peak latency, below); then
#: every interval must be in bound
DRAIN_S = 10.0
MAX_DRAIN_S = 40.0
WATCH_S = 4.0


def _robot(tmp: Path, robot: str, endpoint: str, bundles: bool) -> Path:
    """Every reading sent (no local cache), so the offered load is what the QoS assigns."""
    path = tmp / f"{robot}.toml"
    path.write_text(
        f'robot_id = "{robot}"\nfleet = "itest"\nconnect = ["{endpoint}"]\n'
        'preset = "machine1"\npreset_rate_hz = 50\nstats_period_s = 0.2\n'
        f"bundle_sensors = {str(bundles).lower()}\n"
        "[local_cache]\nenabled = false\n"
    )
    return path


class Watch:
    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.stats: list[tuple[float, CeddpStats]] = []
        self.assignments: list[tuple[float, QosAssignmentMsg]] = []

    def on_stats(self, _key: str, payload: bytes, _att: bytes | None) -> None:
        with self.lock:
            self.stats.append((time.monotonic(), CEDDP_STATS_DECODER.decode(payload)))

    def on_assignment(self, _key: str, payload: bytes, _att: bytes | None) -> None:
        with self.lock:
            self.assignments.append((time.monotonic(), QOS_ASSIGNMENT_DECODER.decode(payload)))

    def overload_epoch(self) -> tuple[float, QosAssignmentMsg] | None:
        with self.lock:
            return next((a for a in self.assignments if a[1].reason.startswith("overload")), None)

    def between(self, t0: float, t1: float) -> list[tuple[float, CeddpStats]]:
        with self.lock:
            return [(at, s) for at, s in self.stats if t0 <= at <= t1]

    def since(self, t: float) -> list[CeddpStats]:
        with self.lock:
            return [s for at, s in self.stats if at >= t]


# with bundles (the configuration perf fleet measures) too: it failed with them before stop 39,
# not understood (docs/protocol.md "Bundles"); it passes since, both before and after a bundled
# robot's sensor writers stopped batching
@pytest.mark.parametrize("bundles", [False, True], ids=["messages", "bundles"])
def test_an_overloaded_ceddp_cuts_the_budget_and_returns_within_its_latency_bound(
    tmp_path: Path, bundles: bool
) -> None:
    watch = Watch()
    with ceddp(tmp_path, extra=CEDDP) as (server, endpoint), client(endpoint) as raw:
        raw.subscribe("arpz/itest/ceddp/stats", watch.on_stats)
        raw.subscribe("arpz/itest/ceddp/qos", watch.on_assignment)
        configs = [_robot(tmp_path, name, endpoint, bundles) for name in ("robot1", "robot2")]
        with robots(tmp_path, configs) as procs:
            wait_until(
                lambda: watch.overload_epoch() is not None,
                timeout_s=40,
                what="a QoS epoch caused by overload",
            )
            cut = watch.overload_epoch()
            assert cut is not None
            cut_at, assignment = cut
            # the assignment in force before the cut: both robots, no budget
            first = [m for at, m in watch.assignments if at < cut_at][-1]
            assert set(first.robots) == {"robot1", "robot2"} and first.budget_hz is None
            # the offered load was about 3x or more what the CEDDP measured it can take
            assert assignment.budget_hz is not None
            capacity = assignment.budget_hz / 0.8  # the default headroom
            offered = sum(6 * q.rate_hz for q in first.robots.values())
            assert offered > 2.5 * capacity, (offered, capacity)
            assert all(
                q.rate_hz < first.robots[r].rate_hz / 2 for r, q in assignment.robots.items()
            )

            def settled() -> bool:
                recent = watch.since(cut_at)[-5:]
                return len(recent) == 5 and all(
                    s.latency_ms_p99 is not None and s.latency_ms_p99 < LATENCY_BOUND_MS
                    for s in recent
                )

            # The backlog drains at what the headroom leaves free (capacity - budget = 0.2 of
            # the capacity), so it takes about 5x the latency it built up: 10 s, or 10x the
            # worst p99 of the 2 s after the cut (the robots apply the new rates only once they
            # get them) where a slower host built a larger backlog, at most MAX_DRAIN_S. After
            # those 2 s the latency must only fall: a cut too small to drain the backlog, or
            # none, lets it grow and fails.
            while not settled():
                since_cut = time.monotonic() - cut_at
                after_cut = watch.between(cut_at - 1.0, cut_at + 2.0)
                peak_ms = max(((s.latency_ms_p99 or 0.0) for _, s in after_cut), default=0.0)
                # (8x failed once by 0.2 %: 17.69 s against 17.66 in a CI that ran 1.25x slow)
                allowed_s = min(MAX_DRAIN_S, max(DRAIN_S, 10 * peak_ms / 1000))
                assert since_cut < allowed_s, (
                    f"latency not back within its bound {allowed_s:.1f} s after the cut "
                    f"(peak p99 {peak_ms:.0f} ms in the 2 s after it)"
                )
                time.sleep(0.05)
            watched_from = time.monotonic()
            time.sleep(WATCH_S)  # deliberately: the fleet must stay within bound for a while
            after = watch.since(watched_from)
            assert len(after) >= WATCH_S / 0.2 / 2, len(after)
            over = [s.latency_ms_p99 for s in after if (s.latency_ms_p99 or 0) > LATENCY_BOUND_MS]
            assert not over, f"p99 over {LATENCY_BOUND_MS} ms after the re-assignment: {over}"
            print(
                f"\noverload: offered {offered:.0f} samples/s, capacity {capacity:.0f}, budget "
                f"{assignment.budget_hz:.0f}; p99 after: "
                f"{max(s.latency_ms_p99 or 0 for s in after):.1f} ms\nreason: {assignment.reason}"
            )
            for proc in procs:
                assert proc.interrupt() == 0, proc.output()
        assert server.interrupt(timeout_s=60) == 0, server.output()
    summary = json.loads((tmp_path / "summary.json").read_text())
    for robot in ("robot1", "robot2"):
        row = summary["robots"][robot]
        assert row["final_stats"], f"{robot}'s final report did not arrive"
        for topic, t in row["topics"].items():
            # what the robot sent either arrived or is counted lost (overwritten in its
            # KEEP_LAST history while the CEDDP was behind, then reported lost): nothing silent
            assert t["sent"] == t["received"] + t["lost"], (robot, topic, t)
            assert t["implausible_lost"] == 0, (robot, topic, t)
        assert all(i["reconciled"] for i in row["incarnations"].values()), row["incarnations"]
    assert summary["overload"]["change_count"] >= 1
    assert "overload" in summary["overload"]["changes"][0]["reason"]
