"""The simulated clock of a robot process: simulated time follows wall time.

The simulator runs inside a real robot process next to real Zenoh traffic, so its time must be
wall time (a reading stamped 1 s ago on the wire is 1 s old in the world too). The time source is
injectable so that tests and the offline runner drive it by hand, without sleeping.
"""

from __future__ import annotations

import time
from collections.abc import Callable


class ManualTime:
    """A time source that only moves when told to: the test double for ``time.monotonic``."""

    def __init__(self, start_s: float = 0.0) -> None:
        self._now_s = start_s

    def __call__(self) -> float:
        return self._now_s

    def advance(self, dt_s: float) -> None:
        if dt_s < 0.0:
            raise ValueError(f"time cannot go backwards: advance({dt_s})")
        self._now_s += dt_s


class SimClock:
    """Seconds of simulated time since the clock was created, following ``time_source``.

    ``tick()`` hands out the time elapsed since the previous tick, so a body can integrate exactly
    the time that passed even when its loop is late (the body sub-steps long gaps itself).
    """

    def __init__(self, time_source: Callable[[], float] = time.monotonic) -> None:
        self._source = time_source
        self._start_s = time_source()
        self._last_tick_s = 0.0

    def now_s(self) -> float:
        return self._source() - self._start_s

    def tick(self) -> float:
        """Seconds since the previous ``tick()`` (or since creation); never negative."""
        now_s = self.now_s()
        dt_s = max(0.0, now_s - self._last_tick_s)
        self._last_tick_s = max(now_s, self._last_tick_s)
        return dt_s
