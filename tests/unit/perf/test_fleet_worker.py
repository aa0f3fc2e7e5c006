"""The fleet worker's one thread for all its robots: each robot's jobs when they are due, and a
robot whose job raises is reported and left out while the others go on."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

from arpz.perf.fleet_worker import run_together, thread_scheduling
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


class _Periodic:
    """A robot whose next job is due ``period_s`` after each run (what ``run_due`` returns)."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self.calls: list[float] = []
        self.next_s = 0.0

    def run_due(self) -> float:
        now = time.monotonic()
        self.calls.append(now)
        if now >= self.next_s:
            self.next_s = now + self.period_s
        return self.next_s - now


def test_a_robot_is_called_when_its_job_is_due_not_whenever_another_s_is() -> None:
    """A fast robot (every 5 ms) beside a slow one (every 200 ms): the slow one is not called
    at the fast one's pace, and neither is called late."""
    fast, slow = _Periodic(0.005), _Periodic(0.2)
    stop, errors = threading.Event(), []
    thread = threading.Thread(
        target=run_together, args=({"fast": fast, "slow": slow}, stop, errors), daemon=True
    )
    thread.start()
    time.sleep(1.0)  # deliberately: a second of both robots' calls
    stop.set()
    thread.join(5)
    assert not thread.is_alive() and errors == []
    assert len(fast.calls) >= 50, len(fast.calls)  # 200 at its period on an idle host
    # 5 due, and a call at least every MAX_WAIT_S (20); at the fast one's pace about 200
    assert len(slow.calls) <= 25, len(slow.calls)
    gaps = [b - a for a, b in zip(slow.calls, slow.calls[1:], strict=False)]
    assert gaps and max(gaps) < 0.2 + 0.3, gaps  # called again, never far past its due time


def test_a_thread_s_scheduling_is_read_from_the_kernel_and_a_gone_thread_is_unknown() -> None:
    """What the report prints as the robots' thread's policy; a thread that has ended (every
    robot failed before it was read) gives "unknown", not an exception that loses the
    worker's counts."""
    here = thread_scheduling(threading.get_native_id())
    policy = {os.SCHED_OTHER: "SCHED_OTHER", os.SCHED_BATCH: "SCHED_BATCH"}[
        os.sched_getscheduler(0)
    ]
    assert here == f"{policy}, nice {os.getpriority(os.PRIO_PROCESS, 0)}", here
    no_such = int(Path("/proc/sys/kernel/pid_max").read_text()) + 1  # no thread has this id
    assert thread_scheduling(no_such).startswith("unknown ("), thread_scheduling(no_such)
    assert thread_scheduling(None) == "unknown"
