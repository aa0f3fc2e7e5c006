"""Graceful overload: the CEDDP measures its own capacity and makes it the fleet's rate budget.

Seed 001 takes Rmax, the rate the server can handle, as a given. A CEDDP that is offered more
than it can ingest lets its queues grow and its latency with them, without bound (25 robots at
100 Hz on a 2-core machine: p50 latency 10-33 s). So the CEDDP measures instead of assuming:

- **load**: the share of each metrics interval in which the sensor path's thread (the reliable
  channel's delivery thread, or the raw ingest worker) was not waiting for samples. A thread
  that never waits is either working or waiting for a CPU or the GIL: either way the CEDDP is
  not keeping up. Latency alone would mislead (a robot whose clock is off, a link that delays);
  the load says the wait is the CEDDP's own.
- **capacity**: samples ingested per second of busy time (rate / load), so it is measured at any
  load, not only when the CEDDP is already overwhelmed.

An interval is *overloaded* when the load is at or above ``busy_bound`` and the pooled p99
latency (robot stamp to ingest) is above ``latency_bound_ms``. After ``trigger_intervals`` of
them in a row, the governor sets the fleet's budget to ``headroom`` x the measured capacity;
the QoS optimiser turns the budget into a lower Rmax (``optimiser.rmax_for_budget``), so every
robot is assigned a lower rate R (a new QoS epoch whose reason carries the measurements). The
governor then holds for ``hold_intervals`` while the backlog drains before it judges again (else the
drain itself, at full load, would cut the budget twice). After ``recover_intervals`` calm
intervals in a row (load below 70 % of the bound, latency below half of it) the budget grows by
``recover_step``, never above ``headroom`` x the capacity measured meanwhile; it is lifted when
the fleet uses less than half of it (robots left, or their sensors slowed down).

Pure: numbers in, a decision out; the metrics ticker feeds it, the control worker applies it.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass

import msgspec

from arpz.core.config import OverloadConfig

#: budget changes kept for the summary (each is an event and a QoS epoch as well)
MAX_CHANGES = 256
#: samples an interval must have ingested for its rate/load to count as a capacity measurement
_MIN_SAMPLES_FOR_CAPACITY = 50
#: below this load the busy time is mostly fixed overhead, not per-sample cost
_MIN_LOAD_FOR_CAPACITY = 0.05
#: weight of a new capacity measurement in the running estimate
_CAPACITY_WEIGHT = 0.5
#: a calm interval: load below this share of ``busy_bound`` and latency below this share of the
#: bound (the hysteresis that keeps budgets from oscillating)
_CALM_SHARE = 0.7
_CALM_LATENCY_SHARE = 0.5
#: saturated intervals whose capacity a cut averages (the latest of a long overloaded run)
_SATURATED_KEPT = 16
#: a budget the fleet uses less than this share of, in calm intervals, no longer binds: lifted
_UNUSED_SHARE = 0.5


@dataclass(frozen=True, slots=True)
class LoadSample:
    """What one metrics interval measured of the sensor path."""

    interval_s: float
    #: sensor samples ingested in the interval
    processed: int
    #: share of the interval the sensor path's thread did not wait for samples, 0..1
    load: float
    #: pooled p99 latency (robot stamp to ingest) of the interval; None when nothing arrived
    latency_ms_p99: float | None


class BudgetChange(msgspec.Struct, frozen=True):
    """A new fleet-wide budget (samples/s into this CEDDP), or None: no budget any more."""

    budget_hz: float | None
    reason: str


class OverloadGovernor:
    """Decides, interval by interval, whether the fleet's rate budget must change."""

    def __init__(self, config: OverloadConfig) -> None:
        self.config = config
        #: samples per busy second, smoothed; None before the first measurement
        self.capacity_hz: float | None = None
        #: the budget in force (samples/s); None: the configured QoS limits alone apply
        self.budget_hz: float | None = None
        self._overloaded_run = 0
        self._calm_run = 0
        self._hold = 0
        #: capacity measured in the latest intervals of the current overloaded run
        self._saturated: deque[float] = deque(maxlen=_SATURATED_KEPT)
        self.last: LoadSample | None = None
        #: every change, oldest first (at most MAX_CHANGES kept; ``change_count`` counts all)
        self.changes: deque[tuple[int, float | None, str]] = deque(maxlen=MAX_CHANGES)
        self.change_count = 0
        #: the highest load and p99 latency seen in an interval
        self.peak_load = 0.0
        self.peak_latency_ms = 0.0

    def summary(self) -> dict[str, object]:
        """For summary.json: what was measured and every budget change with its cause."""
        return {
            "capacity_hz": None if self.capacity_hz is None else round(self.capacity_hz, 1),
            "budget_hz": None if self.budget_hz is None else round(self.budget_hz, 1),
            "peak_load": round(self.peak_load, 4),
            "peak_latency_ms_p99": round(self.peak_latency_ms, 3),
            "change_count": self.change_count,
            "changes": [
                {"stamp_ns": stamp, "budget_hz": budget, "reason": reason}
                for stamp, budget, reason in self.changes
            ],
        }

    def observe(self, sample: LoadSample) -> BudgetChange | None:
        change = self._decide(sample)
        if change is not None:
            self.change_count += 1
            self.changes.append((time.time_ns(), change.budget_hz, change.reason))
        return change

    def _decide(self, sample: LoadSample) -> BudgetChange | None:
        self.last = sample
        self.peak_load = max(self.peak_load, sample.load)
        if sample.latency_ms_p99 is not None:
            self.peak_latency_ms = max(self.peak_latency_ms, sample.latency_ms_p99)
        cfg = self.config
        rate_hz = sample.processed / sample.interval_s if sample.interval_s > 0 else 0.0
        latency = sample.latency_ms_p99
        overloaded = (
            sample.load >= cfg.busy_bound and latency is not None and latency > cfg.latency_bound_ms
        )
        measured: float | None = None
        if sample.processed >= _MIN_SAMPLES_FOR_CAPACITY and sample.load >= _MIN_LOAD_FOR_CAPACITY:
            measured = rate_hz / sample.load
            self.capacity_hz = (
                measured
                if self.capacity_hz is None
                else (1 - _CAPACITY_WEIGHT) * self.capacity_hz + _CAPACITY_WEIGHT * measured
            )
        # a saturated interval measures the capacity directly (the smoothed figure may still
        # carry the lighter load of minutes ago): a cut uses the overloaded run's own mean
        if overloaded and measured is not None:
            self._saturated.append(measured)
        elif not overloaded:
            self._saturated.clear()
        calm = sample.load < _CALM_SHARE * cfg.busy_bound and (
            latency is None or latency < _CALM_LATENCY_SHARE * cfg.latency_bound_ms
        )
        self._overloaded_run = self._overloaded_run + 1 if overloaded else 0
        self._calm_run = self._calm_run + 1 if calm else 0
        if self._hold > 0:
            self._hold -= 1
            return None
        if not cfg.enabled:
            return None
        if self._overloaded_run >= cfg.trigger_intervals and (
            self._saturated or self.capacity_hz is not None
        ):
            return self._shed(sample, rate_hz)
        if self.budget_hz is not None and self._calm_run >= cfg.recover_intervals:
            return self._recover(sample, rate_hz)
        return None

    def _shed(self, sample: LoadSample, rate_hz: float) -> BudgetChange:
        cfg = self.config
        if self._saturated:
            self.capacity_hz = sum(self._saturated) / len(self._saturated)
            self._saturated.clear()
        assert self.capacity_hz is not None
        budget = cfg.headroom * self.capacity_hz
        if self.budget_hz is not None:
            budget = min(budget, self.budget_hz * cfg.headroom)
        self.budget_hz = budget
        self._overloaded_run = 0
        self._hold = cfg.hold_intervals
        return BudgetChange(
            budget,
            f"overload: ingest busy {sample.load:.0%} (bound {cfg.busy_bound:.0%}) and p99 "
            f"latency {sample.latency_ms_p99:.0f} ms (bound {cfg.latency_bound_ms:g} ms) for "
            f"{cfg.trigger_intervals} intervals at {rate_hz:.0f} samples/s; measured capacity "
            f"{self.capacity_hz:.0f} samples/s, budget {budget:.0f} samples/s",
        )

    def _recover(self, sample: LoadSample, rate_hz: float) -> BudgetChange | None:
        cfg = self.config
        assert self.budget_hz is not None
        self._calm_run = 0
        if rate_hz < _UNUSED_SHARE * self.budget_hz:
            self.budget_hz = None
            self._hold = cfg.hold_intervals
            return BudgetChange(
                None,
                f"load recovered: ingest busy {sample.load:.0%} for {cfg.recover_intervals} "
                f"intervals and the fleet sends {rate_hz:.0f} samples/s, under half its budget; "
                "budget lifted, the configured QoS limits apply again",
            )
        # never above what the measurements say the CEDDP can take with headroom
        ceiling = cfg.headroom * (self.capacity_hz or 0.0)
        grown = min(self.budget_hz * cfg.recover_step, ceiling)
        if grown <= self.budget_hz:
            return None
        self.budget_hz = grown
        self._hold = cfg.hold_intervals
        return BudgetChange(
            grown,
            f"load recovered: ingest busy {sample.load:.0%} for {cfg.recover_intervals} "
            f"intervals; measured capacity {self.capacity_hz:.0f} samples/s, budget raised to "
            f"{grown:.0f} samples/s",
        )
