"""Latency distributions with bounded memory: an exact window plus a whole-run log histogram.

``add`` only appends to the current window (it runs once per received sample, so it must be
cheap). Per-interval figures (what the dashboard plots) come from ``take_window`` (exact: the
window's own values), which also folds the window into a histogram of logarithmic buckets, so
whole-run figures (the summary's p50/p99) stay bounded in memory and in time on a week-long
run, and pool across topics by adding counts.

Why a histogram and not a sample of the values: the summary reads every topic's whole-run p50
and p99 every ``summary_period_s``. From uniform reservoirs of 20 000 values (arpz before stop
35 of issue 17) that took sorts of 20 000 values a topic and 160 000 a robot's pooled topics:
190-330 ms every 5 s for 50 robots x 8 topics once the reservoirs were full, on the CEDDP that
also ingests 40 000 samples/s (``python benchmarks/investigations/summary_stall.py --robots 50``).
A histogram
answers in microseconds whatever the count, as HdrHistogram and DDSketch do in the field; the
price is a bounded relative error (``RELATIVE_ERROR``, 1 %) on a value read from it, never on a
count, and the smallest and largest value are kept exactly.
"""

from __future__ import annotations

import math
import threading
from array import array
from collections.abc import Sequence

import numpy as np

#: bucket i of a sign covers [LOWEST_MS * GAMMA**i, LOWEST_MS * GAMMA**(i + 1)); a value read
#: from it is the bucket's relative midpoint, within RELATIVE_ERROR of every value in it
GAMMA = 1.02
RELATIVE_ERROR = (GAMMA - 1) / (GAMMA + 1)
#: magnitudes below this (0.1 us, in ms) count as zero; above HIGHEST_MS (about 28 h), in the
#: top bucket (the exact maximum is kept beside the counts)
LOWEST_MS = 1e-4
HIGHEST_MS = 1e8
_LOG_GAMMA = math.log(GAMMA)
_PER_LOG = 1 / _LOG_GAMMA
_LOG_LOWEST = math.log(LOWEST_MS)
BUCKETS = math.ceil(math.log(HIGHEST_MS / LOWEST_MS) / _LOG_GAMMA)
#: one array for both signs, in value order: negatives (largest magnitude first), zero, positives
_ZERO = BUCKETS
_SLOTS = 2 * BUCKETS + 1
_MAGNITUDES = LOWEST_MS * GAMMA ** np.arange(BUCKETS) * (2 * GAMMA / (GAMMA + 1))
_VALUES = np.concatenate([-_MAGNITUDES[::-1], [0.0], _MAGNITUDES])


class LogHistogram:
    """Counts of values in logarithmic buckets (both signs), with the exact extremes.

    Folding a window is a handful of numpy calls whatever its length; a percentile is a
    cumulative sum over the buckets; pooling topics is adding their counts."""

    __slots__ = ("counts", "high", "low", "not_numbers")

    def __init__(self) -> None:
        self.counts = np.zeros(_SLOTS, dtype=np.int64)
        self.low: float | None = None
        self.high: float | None = None
        #: NaN values offered: in no bucket and no figure, but counted, never dropped silently
        self.not_numbers = 0

    @property
    def total(self) -> int:
        return int(self.counts.sum())

    def add_values(self, values: np.ndarray, weights: np.ndarray | None = None) -> None:
        """Count ``values`` (ms), each once or ``weights`` times (integers, one per value). An
        infinity goes to the outermost bucket of its sign and is the exact extreme; a NaN is
        counted in ``not_numbers`` only. Weights of another length than the values, or a
        negative one (which would take counts away), raise ``ValueError``."""
        if weights is not None and (
            len(weights) != len(values) or (len(weights) and int(weights.min()) < 0)
        ):
            raise ValueError(
                f"weights must be {len(values)} non-negative counts, got {len(weights)} "
                f"(smallest {weights.min() if len(weights) else None})"
            )
        nan = np.isnan(values)
        if nan.any():
            self.not_numbers += int(weights[nan].sum()) if weights is not None else int(nan.sum())
            values = values[~nan]
            weights = weights[~nan] if weights is not None else None
        times = 1 if weights is None else weights.astype(np.int64)
        if not len(values):
            return
        low, high = float(values.min()), float(values.max())
        self.low = low if self.low is None else min(self.low, low)
        self.high = high if self.high is None else max(self.high, high)
        if low >= LOWEST_MS and high < HIGHEST_MS:  # latencies, nearly always
            index = ((np.log(values) - _LOG_LOWEST) * _PER_LOG).astype(np.int64)
            np.minimum(index, BUCKETS - 1, out=index)  # rounding at the top edge
            index += _ZERO + 1
            np.add.at(self.counts, index, times)
            return
        with np.errstate(divide="ignore"):  # log(0) is -inf: the zero bucket
            index = np.floor((np.log(np.abs(values)) - _LOG_LOWEST) * _PER_LOG)
        # clipped as floats, so an infinity never reaches the integer cast
        index = np.clip(index, -1, BUCKETS - 1).astype(np.int64)
        slots = np.where(
            index < 0, _ZERO, np.where(values > 0, _ZERO + 1 + index, _ZERO - 1 - index)
        )
        np.add.at(self.counts, slots, times)

    def copy(self) -> LogHistogram:
        other = LogHistogram()
        other.counts = self.counts.copy()
        other.low, other.high, other.not_numbers = self.low, self.high, self.not_numbers
        return other

    @staticmethod
    def pooled(histograms: Sequence[LogHistogram]) -> LogHistogram:
        """One histogram of every value of ``histograms`` (a robot's topics together)."""
        pooled = LogHistogram()
        for h in histograms:
            pooled.counts += h.counts
            pooled.not_numbers += h.not_numbers
            if h.low is not None:
                pooled.low = h.low if pooled.low is None else min(pooled.low, h.low)
            if h.high is not None:
                pooled.high = h.high if pooled.high is None else max(pooled.high, h.high)
        return pooled

    def quantiles(self, qs: Sequence[float]) -> list[float | None]:
        """Percentiles as ``numpy.percentile`` ("linear") would compute them from the values,
        each value read as its bucket's midpoint (within ``RELATIVE_ERROR``) but the smallest and
        the largest, which are exact (so a single value, or equal ones, come back exactly)."""
        cumulative = np.cumsum(self.counts)
        n = int(cumulative[-1])
        if n == 0 or self.low is None or self.high is None:
            return [None] * len(qs)
        low, high = self.low, self.high
        positions = [(n - 1) * q / 100 for q in qs]
        ranks = sorted({r for p in positions for r in (int(p), min(int(p) + 1, n - 1))})
        slots = np.searchsorted(cumulative, ranks, side="right")
        # each rank's value: its bucket's midpoint within the exact extremes, which the first
        # and the last rank are
        at = {
            rank: low if rank == 0 else high if rank == n - 1 else min(max(value, low), high)
            for rank, value in zip(ranks, _VALUES[slots].tolist(), strict=True)
        }
        out: list[float | None] = []
        for position in positions:
            below = int(position)
            value = at[below]
            if below + 1 < n and position > below:
                value += (at[below + 1] - value) * (position - below)
            out.append(value)
        return out


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
        # benchmarks/investigations/metrics_cost.py``); np.percentile made a 25-robot fleet's
        # summary 15 % of
        # an idle CEDDP's Python time (a py-spy profile, benchmarks/RESULTS.md, issue 17)
        ordered = np.sort(np.asarray(values, dtype=float))
    return [_linear(ordered, q) for q in qs]


def window_max(window: list[float]) -> float | None:
    """The largest number of ``window`` (None: none): a NaN first would make ``max`` return it."""
    top = max(window, default=None)
    if top is not None and top != top:
        top = max((v for v in window if v == v), default=None)
    return top


#: drained windows wait in a flat array until this many values (or a read) before they are
#: folded into the histogram: a fold costs about the same for 50 values as for 4 000, and the
#: metrics tick drains every topic's window twice a second
_FOLD_AT = 4096


class Distribution:
    """A stream of values (ms): the window since the last take, exact, and the whole run in a
    ``LogHistogram``."""

    def __init__(self) -> None:
        self.max: float | None = None
        self._histogram = LogHistogram()
        #: drained windows not yet in the histogram (8 bytes a value, at most ``_FOLD_AT``)
        self._pending = array("d")
        self._window: list[float] = []
        #: guards the histogram: ``fold_window`` runs outside the lock that guards ``add``
        self._lock = threading.Lock()
        self.add = self._window.append  # the hot path: one C call per value

    def take_window(self) -> list[float]:
        """The values added since the last call (and fold them into the whole run's)."""
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
        """Fold a drained window into the whole run's values (any thread)."""
        with self._lock:
            self._fold(window)

    def _drain(self) -> list[float]:
        window = self._window
        self._window = []
        self.add = self._window.append
        return window

    def _fold(self, window: list[float]) -> None:
        top = window_max(window)
        if top is not None:
            self.max = top if self.max is None else max(self.max, top)
        if window:
            self._pending.extend(window)
        if len(self._pending) >= _FOLD_AT:
            self._flush()

    def _flush(self) -> None:
        if self._pending:
            self._histogram.add_values(np.frombuffer(self._pending, dtype=float))
            self._pending = array("d")

    def histogram(self) -> LogHistogram:
        """A copy of the whole run's histogram, every value added so far folded in."""
        with self._lock:
            self._fold(self._drain())
            self._flush()
            return self._histogram.copy()

    def folded(self) -> LogHistogram:
        """A copy of the histogram of every window folded so far (no window drained: that is
        the caller's, under the lock that guards ``add``, with ``drain_window`` and
        ``fold_window``)."""
        with self._lock:
            self._flush()
            return self._histogram.copy()

    def quantile(self, q: float) -> float | None:
        return self.quantiles(q)[0]

    def quantiles(self, *qs: float) -> list[float | None]:
        with self._lock:
            self._fold(self._drain())
            self._flush()
            return self._histogram.quantiles(qs)

    @property
    def count(self) -> int:
        """Values folded so far."""
        with self._lock:
            return self._histogram.total + len(self._pending)

    @property
    def total(self) -> int:
        return self.count + len(self._window)
