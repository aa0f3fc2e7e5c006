"""``Pacer``: the CEDDP's background loops hand the GIL to the sensor path every half millisecond.

The sensor path's delivery thread blocks in Zenoh's FIFO whenever it has caught up, and gives up
the GIL there. A background thread that then runs a long pure-Python loop (the metrics tick over
every topic, the summary, the dashboard's frames and flushes) keeps the GIL until the
interpreter's switch interval (5 ms) makes it let go, and it takes it back as soon as the
delivery thread blocks again: every pass of the sensor path waited up to 5 ms while a loop of
tens of milliseconds ran. At 50 robots x 8 topics x 100 Hz the passes right after each metrics
tick (every 0.5 s, 8-16 ms of CPU) delivered samples that had waited 17-71 ms since the router
took them in, against a p90 of 2-4 ms (issue 17, benchmarks/investigations/README.md, stop 36).

A pacer sleeps a tenth of a millisecond once per ``every_s`` of its loop's work: long enough for
a thread waiting for the GIL to be woken and take it (``time.sleep(0)`` releases it, but the
sleeper usually takes it back before the waiter has been scheduled), short enough that a loop
of 16 ms of CPU gains 32 sleeps of a little more than 0.1 ms each (the timer's slack).
``python benchmarks/investigations/gil_yield.py`` prints how long a thread waits for the GIL back,
paced and
not.
"""

from __future__ import annotations

import time
from collections.abc import Callable

#: how much of its own work a paced loop does between two yields
PACE_EVERY_S = 0.0005
#: how long it yields for: a waiting thread is woken and scheduled well within this
YIELD_S = 0.0001


class Pacer:
    """Call it between the steps of a long loop; every ``every_s`` it yields the GIL."""

    def __init__(
        self,
        every_s: float = PACE_EVERY_S,
        *,
        clock: Callable[[], float] = time.perf_counter,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        if every_s <= 0:
            raise ValueError(f"every_s must be > 0, got {every_s}")
        self.every_s = every_s
        self._clock = clock
        self._sleep = sleep
        self._since = clock()
        #: how many times it yielded (for tests and profiles)
        self.yields = 0

    def __call__(self) -> None:
        if self._clock() - self._since >= self.every_s:
            self._sleep(YIELD_S)
            self.yields += 1
            self._since = self._clock()
