"""WaitMeter: the wait of a thread, counted while it lasts and only while it lasts."""

from __future__ import annotations

import time

import pytest

from arpz.protocol.timers import WaitMeter


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
