"""WaitMeter and BacklogMeter: how long a thread waited, and how long its queue kept messages."""

from __future__ import annotations

import time

import pytest

from arpz.core.percentiles import RELATIVE_ERROR
from arpz.core.protocol.timers import _FOLD_EVERY, BacklogMeter, WaitMeter


def test_a_wait_counts_while_it_lasts_and_work_does_not() -> None:
    meter = WaitMeter()
    assert meter.waited_s == 0.0
    meter.stop()  # a stop without a start adds nothing
    assert meter.waited_s == 0.0
    meter.start()
    time.sleep(0.1)  # deliberately: a wait in progress is read from another point in time
    assert meter.waited_s == pytest.approx(0.1, abs=0.05)
    meter.stop()
    done = meter.waited_s
    time.sleep(0.1)  # deliberately: working, not waiting
    assert meter.waited_s == done
    meter.start()
    time.sleep(0.05)
    meter.stop()
    assert meter.waited_s == pytest.approx(done + 0.05, abs=0.04)


def test_the_backlog_is_the_longest_wait_of_an_interval_and_unknown_is_not_zero() -> None:
    meter = BacklogMeter()
    assert meter.take_max_ns() == 0  # nothing queued: no backlog
    meter.observe(3_000_000)
    meter.observe(1_000_000)
    assert meter.take_max_ns() == 3_000_000
    assert meter.take_max_ns() == 0  # a take starts the next interval
    meter.observe(None)  # queued, but the transport could not tell for how long
    assert meter.take_max_ns() is None
    assert meter.worst_known_ns == 3_000_000  # the worst that could be told still stands
    meter.observe(None)
    meter.observe(2_000_000)
    assert meter.take_max_ns() == 2_000_000  # some waits known: their longest
    fresh = BacklogMeter()
    fresh.observe(None)
    assert fresh.worst_known_ns is None


def test_every_timed_wait_enters_the_run_s_percentiles() -> None:
    meter = BacklogMeter()
    assert meter.quantiles_ms(50, 99) == [None, None]
    for ms in range(1, 101):  # 1..100 ms
        meter.observe(ms * 1_000_000)
    meter.observe(None)  # untimed: in no percentile
    p50, p99 = meter.quantiles_ms(50, 99)
    assert p50 == pytest.approx(50.5, rel=RELATIVE_ERROR)
    assert p99 == pytest.approx(99.01, rel=RELATIVE_ERROR)
    assert meter.take_max_ns() == 100_000_000
    meter.observe(500_000_000)
    assert meter.quantiles_ms(100) == [pytest.approx(500.0)]


def test_a_meter_whose_maximum_nobody_takes_keeps_its_window_bounded() -> None:
    """A robot's readers observe their backlog but nothing takes it: the waits are folded
    into the bounded sample as they come, not kept in a list that grows for the whole run."""
    meter = BacklogMeter()
    for _ in range(3 * _FOLD_EVERY + 5):
        meter.observe(1_000_000)
    waits = meter._waits_ms
    assert waits is not None and waits.total - waits.count == 5  # unfolded: the remainder only
    assert waits.count == 3 * _FOLD_EVERY
