"""Latency distributions with bounded memory: an exact window plus a uniform reservoir.

``add`` only appends to the current window (it runs once per received sample, so it must be
cheap). Per-interval figures (what the dashboard plots) come from ``take_window``, which also
folds the window into a uniform reservoir of at most ``capacity`` values (Vitter's algorithm R,
vectorised with numpy), so whole-run figures (the summary's p50/p99) stay bounded in memory on
a week-long run.
"""

from __future__ import annotations

import threading

import numpy as np

#: values a whole-run distribution keeps: its p99 then rests on 200 values of the tail. The
#: summary's quantiles are computed under the ingest lock every ``summary_period_s``: with full
#: reservoirs of 100 000 values, 10 robots of 8 topics held it about 0.7 s each time, a latency
#: tail for every robot (``python benchmarks/summary_stall.py`` prints both)
DEFAULT_CAPACITY = 20_000


#: below this many values a plain sort beats numpy, whose percentile costs 20-40 us a call
#: whatever the size: a metrics tick of 80 topics spent 5.9 ms on 50-value windows, holding the
#: GIL the ingest needs (issue 17)
_SMALL = 2048


def _linear(ordered: list[float] | np.ndarray, q: float) -> float:
    """numpy's default ("linear") percentile of sorted values: interpolate at (n - 1) q / 100."""
    position = (len(ordered) - 1) * q / 100
    low = int(position)
    if low + 1 >= len(ordered):
        return float(ordered[-1])
    return float(ordered[low] + (ordered[low + 1] - ordered[low]) * (position - low))


def percentile(values: list[float] | np.ndarray, q: float) -> float | None:
    return percentiles(values, (q,))[0]


def percentiles(values: list[float] | np.ndarray, qs: tuple[float, ...]) -> list[float | None]:
    """Several percentiles of the same values in one pass (one sort or partition, not one
    each), as ``numpy.percentile`` computes them."""
    if len(values) == 0:
        return [None] * len(qs)
    if isinstance(values, list) and len(values) <= _SMALL:
        ordered: list[float] | np.ndarray = sorted(values)
    else:
        # np.sort and an interpolation by hand, not np.percentile: on a reservoir of 20 000 values
        # 120 us against 409, on a slow topic's 45 values 6 us against 70 (``python
        # benchmarks/metrics_cost.py``); np.percentile made a 25-robot fleet's summary 15 % of
        # an idle CEDDP's Python time (a py-spy profile, benchmarks/RESULTS.md, issue 17)
        ordered = np.sort(np.asarray(values, dtype=float))
    return [_linear(ordered, q) for q in qs]


class Distribution:
    def __init__(self, capacity: int = DEFAULT_CAPACITY, seed: int = 0) -> None:
        self.capacity = capacity
        self.count = 0
        self.max: float | None = None
        self._reservoir = np.empty(0, dtype=float)
        self._window: list[float] = []
        self._rng = np.random.default_rng(seed)
        #: guards the reservoir: ``fold_window`` runs outside the lock that guards ``add``
        self._lock = threading.Lock()
        self.add = self._window.append  # the hot path: one C call per value

    def take_window(self) -> list[float]:
        """The values added since the last call (and fold them into the reservoir)."""
        window = self._drain()
        self.fold_window(window)
        return window

    def drain_window(self) -> list[float]:
        """The values added since the last call, not yet folded: one list swap, cheap enough to
        run under the lock that guards ``add`` (the CEDDP's ingest lock). Pass the window to
        ``fold_window`` once that lock is released: with 80 topics, folding and computing every
        window's percentiles under it held the ingest for 12-16 ms every 0.5 s, a p99 latency
        of about 20 ms for every robot (issue 17)."""
        return self._drain()

    def fold_window(self, window: list[float]) -> None:
        """Fold a drained window into the whole-run reservoir (any thread)."""
        with self._lock:
            self._fold(window)

    def _drain(self) -> list[float]:
        window = self._window
        self._window = []
        self.add = self._window.append
        return window

    def _fold(self, window: list[float]) -> None:
        if not window:
            return
        values = np.asarray(window, dtype=float)
        top = float(values.max())
        self.max = top if self.max is None else max(self.max, top)
        room = self.capacity - len(self._reservoir)
        if room > 0:
            self._reservoir = np.concatenate([self._reservoir, values[:room]])
            self.count += min(room, len(values))
            values = values[room:]
        if len(values):
            # algorithm R: the i-th value overall replaces a random slot with probability cap/i
            positions = self.count + 1 + np.arange(len(values))
            slots = (self._rng.random(len(values)) * positions).astype(np.int64)
            keep = slots < self.capacity
            self._reservoir[slots[keep]] = values[keep]
            self.count += len(values)

    def sample(self) -> list[float]:
        """A uniform sample of every value added (all of them while below capacity)."""
        with self._lock:
            self._fold(self._drain())
            return [float(v) for v in self._reservoir]

    def values(self) -> np.ndarray:
        """The same sample as ``sample``, as the array itself (no Python float per value: the
        summary, written every few seconds, merges these without churning the heap)."""
        with self._lock:
            self._fold(self._drain())
            # a copy: the metrics thread may fold the next window in place meanwhile
            return self._reservoir.copy()

    def folded(self) -> np.ndarray:
        """A copy of the reservoir as folded so far (no window drained: that is the caller's,
        under the lock that guards ``add``, with ``drain_window`` and ``fold_window``)."""
        with self._lock:
            return self._reservoir.copy()

    def quantile(self, q: float) -> float | None:
        with self._lock:
            self._fold(self._drain())
            return percentile(self._reservoir, q)

    def quantiles(self, *qs: float) -> list[float | None]:
        with self._lock:
            self._fold(self._drain())
            return percentiles(self._reservoir, qs)

    @property
    def total(self) -> int:
        return self.count + len(self._window)
