"""The fleet worker's one thread for all its robots: each robot's jobs when they are due, and a
robot whose job raises is reported and left out while the others go on."""

from __future__ import annotations

import threading

from arpz.perf.fleet_worker import run_together
from tests.support import wait_until


class _Agent:
    def __init__(self, fail_after: int | None = None) -> None:
        self.runs = 0
        self.fail_after = fail_after

    def run_due(self) -> float:
        self.runs += 1
        if self.fail_after is not None and self.runs > self.fail_after:
            raise RuntimeError("a driver broke")
        return 0.001


def test_one_thread_runs_every_robot_and_a_failing_one_is_reported_and_left_out() -> None:
    agents = {"r1": _Agent(), "r2": _Agent(fail_after=3), "r3": _Agent()}
    stop, errors = threading.Event(), []
    thread = threading.Thread(target=run_together, args=(agents, stop, errors), daemon=True)
    thread.start()
    try:
        wait_until(lambda: agents["r1"].runs > 50 and agents["r3"].runs > 50, what="runs")
    finally:
        stop.set()
        thread.join(5)
    assert not thread.is_alive()
    assert agents["r2"].runs == 4  # three runs, then the one that raised, then left out
    assert errors == ["r2: run failed: RuntimeError('a driver broke')"]
