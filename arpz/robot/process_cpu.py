"""The robot process's CPU time, read at most every ``MIN_INTERVAL_S`` and shared by every
agent of the process.

Why not ``time.process_time()`` at each report: Linux sums the CPU time of every thread of the
process on each read (``CLOCK_PROCESS_CPUTIME_ID``), with the GIL held. A robot process has
about 60 threads (its channels' workers and zenoh-python's callback threads), where a read
costs a few microseconds; a ``python -m arpz.perf fleet`` worker packs a dozen robots into one
process of 750 threads, where it cost 75 us (median; p90 148) while those threads woke, for
each of the dozen robots' two reports a second, all on the thread that runs the robots' sensing
(``python benchmarks/investigations/process_cpu_cost.py``). The robots of one process report that
process's
CPU in either case; read once, it is the same figure.
"""

from __future__ import annotations

import threading
import time

#: a reading younger than this is reused (robots report every ``stats_period_s``, 0.5 s)
MIN_INTERVAL_S = 0.2


class ProcessCpu:
    """``read()``: (monotonic seconds, process CPU seconds) of one reading, shared."""

    def __init__(self, min_interval_s: float = MIN_INTERVAL_S) -> None:
        self._min_interval_s = min_interval_s
        self._lock = threading.Lock()
        self._reading = (time.monotonic(), time.process_time())

    def read(self) -> tuple[float, float]:
        with self._lock:
            if time.monotonic() - self._reading[0] >= self._min_interval_s:
                self._reading = (time.monotonic(), time.process_time())
            return self._reading


#: the one reader of this process
PROCESS_CPU = ProcessCpu()


def cpu_percent(last: tuple[float, float], now: tuple[float, float]) -> float | None:
    """CPU between two readings, in percent of one core; None when they are the same reading
    (a caller asking again within ``MIN_INTERVAL_S`` keeps its previous figure)."""
    elapsed_s = now[0] - last[0]
    if elapsed_s <= 0:
        return None
    return 100.0 * (now[1] - last[1]) / elapsed_s
