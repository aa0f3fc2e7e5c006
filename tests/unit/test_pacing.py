"""The CEDDP's background loops yield the GIL once per half millisecond of their own work."""

from __future__ import annotations

import statistics
import sys

import pytest

from arpz.ceddp.pacing import YIELD_S, Pacer
from tests.support import gil_waits_ms


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0
        self.slept: list[float] = []

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.slept.append(seconds)
        self.now += seconds


def test_yields_once_per_period_of_work_and_not_before() -> None:
    clock = FakeClock()
    pace = Pacer(0.001, clock=clock, sleep=clock.sleep)
    for _ in range(9):  # 0.9 ms of work: no yield yet
        clock.now += 0.0001
        pace()
    assert clock.slept == []
    clock.now += 0.0001
    pace()
    assert clock.slept == [YIELD_S]
    # the period counts from the end of the yield, not from its start
    clock.now += 0.0009
    pace()
    assert pace.yields == 1
    clock.now += 0.0002
    pace()
    assert pace.yields == 2


def test_rejects_a_period_that_is_not_positive() -> None:
    with pytest.raises(ValueError, match="every_s"):
        Pacer(0.0)


def test_a_paced_loop_lets_a_waiting_thread_run_sooner() -> None:
    """Real threads: a thread that gives up the GIL for a moment while a pure-Python loop runs
    gets it back within about a yield with a pacer, not after CPython's switch interval."""

    def typical_wait(pace: Pacer | None) -> float:
        # the median: a scheduling hiccup of a loaded host moves the worst, not the typical
        return statistics.median(gil_waits_ms(pace, 0.2) or [0.0])

    unpaced = min(typical_wait(None) for _ in range(3))
    paced = min(typical_wait(Pacer()) for _ in range(3))
    # unpaced, the waiter gets the GIL only when CPython's switch interval (5 ms) forces the
    # loop out; paced, within about a yield (0.5 ms)
    assert unpaced >= 0.8 * sys.getswitchinterval() * 1e3  # ms, as the waits
    assert paced < 0.6 * unpaced
