"""Clocks and the pure timers behind DEADLINE and LIVELINESS.

The state machines read time only through a ``Clock`` so tests can drive them with ``FakeClock``
and get the same result on every run; the timers take the current time as an argument.
"""

from __future__ import annotations

import threading
import time
from array import array
from typing import Protocol

import numpy as np

from arpz.core.percentiles import Distribution, LogHistogram


class Clock(Protocol):
    def monotonic_s(self) -> float: ...
    def wall_ns(self) -> int: ...


class SystemClock:
    """Monotonic time for timers; wall time for source stamps (comparable across hosts).

    The C functions themselves, not wrappers: they are called on every sample."""

    monotonic_s = staticmethod(time.monotonic)
    wall_ns = staticmethod(time.time_ns)


class FakeClock:
    def __init__(self, start_s: float = 1000.0) -> None:
        self.now_s = start_s

    def monotonic_s(self) -> float:
        return self.now_s

    def wall_ns(self) -> int:
        return int(self.now_s * 1e9)

    def advance(self, dt_s: float) -> None:
        self.now_s += dt_s


class DeadlineTimer:
    """Counts missed deadline periods: silent for 3.5 periods = 3 misses, reported as they happen.

    A period of 0 disables the timer (no deadline).
    """

    def __init__(self, period_s: float, now_s: float) -> None:
        self.period_s = period_s
        self.last_s = now_s
        self.reported = 0
        self.total = 0

    def reset(self, now_s: float) -> int:
        """A sample (or proof of an unchanged value) arrived: returns the misses since the last
        poll first, so a late timer never forgets a period that did pass without one."""
        new = self.poll(now_s)
        self.last_s = now_s
        self.reported = 0
        return new

    def poll(self, now_s: float) -> int:
        """New misses since the last poll."""
        if self.period_s <= 0:
            return 0
        missed = int((now_s - self.last_s) / self.period_s)
        new = missed - self.reported
        if new <= 0:
            return 0
        self.reported = missed
        self.total += new
        return new


class LeaseTimer:
    """Alive while asserted within the lease; a lease of 0 never expires."""

    def __init__(self, lease_s: float, now_s: float) -> None:
        self.lease_s = lease_s
        self.last_s = now_s
        self.alive = True

    def assert_alive(self, now_s: float) -> bool:
        """Record an assertion; True if this brought a not-alive peer back."""
        self.last_s = now_s
        if self.alive:
            return False
        self.alive = True
        return True

    def poll(self, now_s: float) -> bool:
        """True exactly once when the lease expires."""
        if self.lease_s <= 0 or not self.alive:
            return False
        if now_s - self.last_s > self.lease_s:
            self.alive = False
            return True
        return False


class WaitMeter:
    """How long one thread has waited (for data) so far, the wait in progress included.

    The thread brackets each blocking receive with ``start`` and ``stop``; any other thread
    reads ``waited_s``. A server judges its own load from the growth of ``waited_s`` over an
    interval (arpz/ceddp/overload.py): what the thread did not wait, it worked, or waited for a
    CPU. Reads race the writer by design (two floats, no lock): a read may miss or double one
    wait at its boundary, which callers clamp.
    """

    def __init__(self) -> None:
        self._done_s = 0.0
        #: perf_counter when the current wait began; 0.0 while the thread works
        self._since = 0.0

    def start(self) -> None:
        self._since = time.perf_counter()

    def stop(self) -> None:
        since, self._since = self._since, 0.0
        if since:
            self._done_s += time.perf_counter() - since

    @property
    def waited_s(self) -> float:
        since = self._since
        done = self._done_s
        return done + (time.perf_counter() - since if since else 0.0)


#: observed waits a ``BacklogMeter`` keeps unfolded at most (a fold of this many: about 0.1 ms)
_FOLD_EVERY = 4096


class BacklogMeter:
    """The longest a message waited in the receive queue before the receiving thread took it,
    since the last ``take_max_ns``: a receiver's backlog in time (a queue's depth is its
    transport's to know, and Zenoh's FIFO does not say). The receiving thread observes the
    first message of each pull that found the queue non-empty (the oldest waiting); one other
    thread takes the maximum (a stats interval). No lock for the maximum: an observation that
    races the take may land in either interval. Every timed wait also enters a bounded
    whole-run sample (``quantiles_ms``), under a lock of its own.

    A message whose wait the transport cannot tell (``None``: a Zenoh sample without a
    timestamp, when the router's timestamping is turned off) makes the figure unknown, not 0:
    "no backlog" must not be reported for a queue nobody could measure."""

    def __init__(self) -> None:
        self._max_ns = 0
        self._unknown = False
        #: the longest wait since the meter started, for a run's summary
        self.worst_ns = 0
        #: whether any queued message's wait could not be told since the meter started
        self.ever_unknown = False
        #: every observed wait, ms, in a bounded whole-run sample: whether a p99 latency is
        #: spent in this queue or before it, which the maximum cannot say. Folded every
        #: ``_FOLD_EVERY`` observations by the observing thread, so that a receiver whose
        #: maximum nobody takes (a robot's reader) keeps a bounded window too
        self._waits_ms: Distribution | None = None  # made at the first timed wait
        self._unfolded = 0
        self._waits_lock = threading.Lock()

    def observe(self, waited_ns: int | None) -> None:
        if waited_ns is None:
            self._unknown = self.ever_unknown = True
            return
        with self._waits_lock:
            if self._waits_ms is None:  # a writer's meter, or an inline reader's, never gets here
                self._waits_ms = Distribution()
            self._waits_ms.add(waited_ns / 1e6)
            self._unfolded += 1
            if self._unfolded >= _FOLD_EVERY:
                self._waits_ms.take_window()
                self._unfolded = 0
        if waited_ns > self._max_ns:
            self._max_ns = waited_ns
            if waited_ns > self.worst_ns:
                self.worst_ns = waited_ns

    def take_max_ns(self) -> int | None:
        """The longest wait observed since the previous take (0: nothing queued; None: only
        waits that could not be told), and start anew."""
        worst, unknown = self._max_ns, self._unknown
        self._max_ns, self._unknown = 0, False
        return None if unknown and not worst else worst

    def quantiles_ms(self, *qs: float) -> list[float | None]:
        """Percentiles of every timed wait since the meter started, ms (None: none timed)."""
        with self._waits_lock:
            if self._waits_ms is None:
                return [None] * len(qs)
            self._unfolded = 0
            return self._waits_ms.quantiles(*qs)

    @property
    def worst_known_ns(self) -> int | None:
        """``worst_ns``, or None if no wait could be told but some went unmeasured."""
        return None if self.ever_unknown and not self.worst_ns else self.worst_ns


#: passes a ``SojournMeter`` keeps in flat arrays before it folds them into its histogram
_SOJOURN_FOLD_AT = 4096


class SojournMeter:
    """How long the samples of each delivery pass had been in this process: from the moment the
    transport received the pass's oldest sample (a Zenoh router's timestamp: exact when the
    router is this process, a CEDDP) until every sample of the pass had been handed to
    ``on_data`` and it had returned. The server's own share of a sample's latency, which an
    end-to-end percentile cannot tell from the robots' CPU and the link: at 50 robots on one
    2-core host the CEDDP's queue wait at each pull (``BacklogMeter``) said 3-13 ms at p99
    while the samples' time inside the CEDDP was 17-58 ms at p99 (issue 17, stop 36).

    Every message of a pass (a sample, or a writer's batch of them) counts with the pass's
    oldest one's figure: an upper bound of each one's, read once per pass (not a call into
    Zenoh for every message's timestamp on the sensor path). The delivery thread observes; any
    thread reads, under the lock. A pass the transport could not time (no router timestamp)
    counts in ``unknown_samples`` and in no percentile."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._histogram = LogHistogram()
        self._values = array("d")
        self._weights = array("q")
        #: the longest figure since start, ns, and the samples measured and not measurable
        #: (no timestamp: the router's timestamping turned off)
        self.worst_ns = 0
        self.samples = 0
        self.unknown_samples = 0

    def observe(self, sojourn_ns: int | None, samples: int) -> None:
        if samples <= 0:
            return
        if sojourn_ns is None:
            self.unknown_samples += samples
            return
        sojourn_ns = max(0, sojourn_ns)
        with self._lock:
            self.samples += samples
            if sojourn_ns > self.worst_ns:
                self.worst_ns = sojourn_ns
            self._values.append(sojourn_ns / 1e6)
            self._weights.append(samples)
            if len(self._values) >= _SOJOURN_FOLD_AT:
                self._fold()

    def _fold(self) -> None:
        if self._values:
            self._histogram.add_values(
                np.frombuffer(self._values, dtype=float), np.frombuffer(self._weights, np.int64)
            )
            self._values, self._weights = array("d"), array("q")

    def quantiles_ms(self, *qs: float) -> list[float | None]:
        """Percentiles over the samples measured since start, ms (None: none measured)."""
        with self._lock:
            self._fold()
            return self._histogram.quantiles(qs)

    @property
    def worst_ms(self) -> float | None:
        """The longest figure since start, ms (None: no sample measured)."""
        return self.worst_ns / 1e6 if self.samples else None
