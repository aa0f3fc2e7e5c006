"""One log line per cause per interval, with the count of what was not logged."""

from __future__ import annotations

import logging

import pytest

from arpz.core.throttled_log import OTHER_CAUSES, ThrottledLog


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_one_line_per_cause_per_interval_with_the_count(caplog: pytest.LogCaptureFixture) -> None:
    clock = Clock()
    log = ThrottledLog(logging.getLogger("t"), interval_s=10, clock=clock)
    with caplog.at_level(logging.WARNING, logger="t"):
        for i in range(1000):
            clock.now = i * 0.01  # 1000 bad messages in 10 s
            log.warning("bad stats from r2", "bad stats from %s", "r2")
            log.warning("bad announce from r2", "bad announce from %s", "r2")
        clock.now = 10.5
        assert log.warning("bad stats from r2", "bad stats from %s", "r2")
    lines = [r.getMessage() for r in caplog.records]
    assert lines == [
        "bad stats from r2",
        "bad announce from r2",
        "bad stats from r2 (and 999 more like it in the last 10 s)",
    ]
    assert log.suppressed == 999 * 2


def test_a_traceback_only_on_the_first_line_and_causes_are_bounded(
    caplog: pytest.LogCaptureFixture,
) -> None:
    clock = Clock()
    log = ThrottledLog(logging.getLogger("t2"), interval_s=1, max_causes=2, clock=clock)
    with caplog.at_level(logging.ERROR, logger="t2"):
        for t in (0.0, 2.0):
            clock.now = t
            try:
                raise ValueError("boom")
            except ValueError:
                log.exception("fail", "failed")
    assert [bool(r.exc_info) for r in caplog.records] == [True, False]
    for cause in ("a", "b", "c", "d"):  # beyond max_causes, all share one cause
        log.warning(cause, cause)
    assert set(log._causes) == {"fail", "a", OTHER_CAUSES}
