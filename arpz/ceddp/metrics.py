"""The CEDDP's metrics ticker: every ``metrics_period_s``, the counters of the interval.

One thread turns the ingest's per-topic counters and the robots' last reports into a
``MetricsFrame`` for the dashboard (rates, latency and staleness percentiles of the interval,
loss, cache control, the downlink), publishes ``CeddpStats`` (what any client can read of the
CEDDP's load), ticks the planners, and every ``summary_period_s`` persists the summary so that a
CEDDP killed with -9 leaves one to reconcile against.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from arpz.ceddp.clock_service import ClockWatch
from arpz.ceddp.control import RobotRecord
from arpz.ceddp.downlink import Downlink
from arpz.ceddp.identity import Identity
from arpz.ceddp.ingest import Ingest
from arpz.ceddp.overload import BudgetChange, LoadSample, OverloadGovernor
from arpz.ceddp.pacing import Pacer
from arpz.ceddp.planner import Planner
from arpz.channel.io import Outlet
from arpz.core.config import CeddpConfig
from arpz.core.errors import ArpzError
from arpz.core.frames import DashboardLike, MetricsFrame
from arpz.core.messages import CeddpStats, TopicRate, encode
from arpz.core.percentiles import percentile, percentiles
from arpz.core.throttled_log import ThrottledLog

log = logging.getLogger(__name__)
throttled = ThrottledLog(log)


class MetricsTicker:
    """Thread: ``run`` is the metrics ticker (``arpz-metrics``); ``tick`` also runs once more at
    shutdown, on the caller's thread, after the workers stopped."""

    def __init__(
        self,
        config: CeddpConfig,
        ingest: Ingest,
        robots: dict[str, RobotRecord],
        sink: Downlink,
        planners: list[Planner],
        dashboard: DashboardLike | None,
        *,
        refused: Callable[[], dict[str, dict[str, int]]],
        persist_partial: Callable[[], None],
        sensor_path: Callable[[], tuple[int, float]] = lambda: (0, 0.0),
        backlog_ms: Callable[[], float | None] = lambda: None,
        on_budget: Callable[[BudgetChange], None] = lambda change: None,
        clock: ClockWatch | None = None,
        identity: Identity | None = None,
    ) -> None:
        self.config = config
        self.ingest = ingest
        self.robots = robots
        self.sink = sink
        self.planners = planners
        self.dashboard = dashboard
        self._refused = refused
        self._persist_partial = persist_partial
        #: (samples ingested so far, seconds the sensor path waited for samples so far)
        self._sensor_path = sensor_path
        #: the longest a sample waited before the sensor path took it, since the last call
        self._backlog_ms = backlog_ms
        self._on_budget = on_budget
        #: robots' clock offsets (frames: clock_offset_ms, clock_delay_ms; CeddpStats)
        self.clock = clock
        #: versions and security, for CeddpStats
        self.identity = identity
        self.governor = OverloadGovernor(config.overload)
        self._last_path = sensor_path()
        #: where CeddpStats go (opened by the server at start)
        self.stats_out: Outlet | None = None
        #: the last interval's frame (None before the first tick): what the status page and
        #: /metrics show of rates and percentiles (docs/tools.md "Live views"); replaced, never
        #: changed
        self.last_frame: MetricsFrame | None = None
        #: called with every frame on this thread; each must return at once (a queue put)
        self.frame_listeners: list[Callable[[MetricsFrame], None]] = []
        self._last: tuple[float, float, dict[tuple[str, str], tuple[int, int]]] = (
            time.monotonic(),
            time.process_time(),
            {},
        )

    def run(self, stop: threading.Event) -> None:
        period_s = self.config.summary_period_s
        next_persist = time.monotonic() + period_s
        while not stop.wait(self.config.metrics_period_s):
            try:
                self.tick()
                if period_s and time.monotonic() >= next_persist:
                    # a CEDDP killed with -9 leaves this one: "complete": false, at most
                    # summary_period_s old, reconcilable against the next run's
                    next_persist = time.monotonic() + period_s
                    self._persist_partial()
            except Exception:  # a bug in one tick must not stop the reporting
                throttled.exception("metrics tick", "metrics tick failed")

    def tick(self) -> None:
        now, cpu = time.monotonic(), time.process_time()
        last_now, last_cpu, last_counts = self._last
        interval_s = max(now - last_now, 1e-6)
        frame_topics: dict[tuple[str, str], dict[str, float]] = {}
        refused = self._refused()
        written: dict[str, int] = {}
        for (robot, _), counters in self.sink.snapshot().items():
            written[robot] = written.get(robot, 0) + counters.written
        rates: list[TopicRate] = []
        counts: dict[tuple[str, str], tuple[int, int]] = {}
        latencies: list[float] = []
        # Under the ingest lock only what must be consistent: each topic's counters and its
        # window drained (a list swap). The rows, folds and percentiles come after it is
        # released, paced: built under it (rows of 400 topics), every robot's samples waited
        # for the tick, and the passes after each tick delivered samples 17-71 ms old (stop 36).
        with self.ingest.lock:
            taken = [
                (
                    slot,
                    m,
                    m.received,
                    m.bytes,
                    m.lost,
                    m.before_join,
                    m.decode_errors,
                    self.ingest.cache_counters(*slot).hits,
                    m.latency_ms.drain_window(),
                    m.staleness_ms.drain_window(),
                )
                for slot, m in self.ingest.topics.items()
            ]
            records = {robot: record.stats for robot, record in self.robots.items()}
            # one robot_id in two processes (arpz/ceddp/control.py): "robot: kept, dropped"
            moment = time.monotonic()
            duplicates = {
                robot: [f"{robot}: {record.incarnation}, {name}" for name in live]
                for robot, record in self.robots.items()
                if (live := record.live_duplicates(moment))
            }
            incompatible = [
                f"{robot}: {line}"
                for robot, record in self.robots.items()
                for line in record.incompatible
            ][:64]
        pace = Pacer()
        for (
            slot,
            m,
            received,
            nbytes,
            lost,
            before_join,
            decode_errors,
            hits,
            window,
            stale,
        ) in taken:
            pace()
            received0, bytes0 = last_counts.get(slot, (0, 0))
            counts[slot] = (received, nbytes)
            row = {
                "rate_hz": (received - received0) / interval_s,
                "bytes_per_s": (nbytes - bytes0) / interval_s,
                "lost": float(lost),
                "cc_discarded": float(hits),
                "decode_errors": float(decode_errors),
            }
            stats = records.get(slot[0])
            if stats is not None and slot[1] in stats.topics:
                row["held_back"] = float(stats.topics[slot[1]].held_back)
            rates.append(
                TopicRate(
                    robot=slot[0],
                    topic=slot[1],
                    rate_hz=row["rate_hz"],
                    bytes_per_s=row["bytes_per_s"],
                    lost=lost + before_join,
                )
            )
            m.latency_ms.fold_window(window)
            m.staleness_ms.fold_window(stale)
            latencies.extend(window)
            if window:  # both from one partition of the window
                p50, p99 = percentiles(window, (50, 99))
                row["latency_ms_p50"] = p50 or 0.0
                row["latency_ms_p99"] = p99 or 0.0
            if stale:
                row["staleness_ms_p99"] = percentile(stale, 99) or 0.0
            frame_topics[slot] = row
        robots: dict[str, dict[str, float]] = {}
        for robot, robot_stats in records.items():
            if robot_stats is None:
                continue
            pace()
            row = {"cpu_percent": robot_stats.cpu_percent}
            if robot_stats.qos_rate_hz is not None:
                row["qos_rate_hz"] = robot_stats.qos_rate_hz
            if robot_stats.qos_depth is not None:
                row["qos_depth"] = float(robot_stats.qos_depth)
            hello = robot_stats.hello
            if hello is not None and hello.rtt_ms_p50 is not None:
                row["hello_rtt_ms_p50"] = hello.rtt_ms_p50
            inbound = robot_stats.inbound.values()
            row["downlink_lost"] = float(sum(c.lost + c.lifespan_expired for c in inbound))
            row["watchdog_stops"] = float(sum(robot_stats.watchdog_stops.values()))
            # the health of its sensors: reads that gave no reading, sensors with none lately
            row["driver_errors"] = float(sum(c.driver_errors for c in robot_stats.topics.values()))
            row["silent_sensors"] = float(len(robot_stats.silent_sensors))
            row["duplicate_processes"] = float(len(duplicates.get(robot, ())))
            row["downlink_written"] = float(written.get(robot, 0))
            if self.clock is not None:
                row.update(self.clock.frame_row(robot))
            robots[robot] = row
        flagged = self.clock.flagged() if self.clock is not None else []
        for robot, per_key in refused.items():
            robots.setdefault(robot, {})["refused"] = float(sum(per_key.values()))
        self._last = (now, cpu, counts)
        cpu_percent = 100.0 * (cpu - last_cpu) / interval_s
        load = self._judge_load(interval_s, percentile(latencies, 99) if latencies else None)
        ceddp_row = robots.setdefault("ceddp", {})
        ceddp_row["cpu_percent"] = cpu_percent
        ceddp_row["ingest_load"] = load.load
        backlog_ms = self._backlog_ms()
        if backlog_ms is not None:
            ceddp_row["ingest_backlog_ms"] = backlog_ms
        if self.governor.capacity_hz is not None:
            ceddp_row["capacity_hz"] = self.governor.capacity_hz
        if self.governor.budget_hz is not None:
            ceddp_row["budget_hz"] = self.governor.budget_hz
        frame = MetricsFrame(time.time_ns(), frame_topics, robots)
        self.last_frame = frame
        if self.dashboard is not None:
            self.dashboard.submit(frame)
        for listener in self.frame_listeners:
            listener(frame)
        try:
            if self.stats_out is not None:
                governor = self.governor
                report = CeddpStats(
                    stamp_ns=time.time_ns(),
                    cpu_percent=round(cpu_percent, 2),
                    topics=rates,
                    processed=load.processed,
                    load=round(load.load, 4),
                    ingest_backlog_ms=None if backlog_ms is None else round(backlog_ms, 3),
                    latency_ms_p99=load.latency_ms_p99,
                    capacity_hz=governor.capacity_hz,
                    budget_hz=governor.budget_hz,
                    dashboard_dropped=self.dashboard.dropped if self.dashboard else 0,
                    incompatible_qos=incompatible,
                    clock_corrected=self.clock is not None and self.clock.config.correct,
                    clock_max_offset_ms=(
                        self.clock.config.max_offset_ms if self.clock is not None else None
                    ),
                    clock_flagged=flagged,
                    duplicate_robots=[line for lines in duplicates.values() for line in lines],
                    **self._identity_fields(),
                )
                self.stats_out.send(encode(report), report.stamp_ns)
        except ArpzError as exc:  # the session may be closing, or a full history refused it
            log.debug("could not publish CEDDP stats: %s", exc)
        for planner in self.planners:
            planner.tick(now)

    def _identity_fields(self) -> dict[str, Any]:
        identity = self.identity
        if identity is None:
            return {}
        return {
            "arpz_version": identity.arpz_version,
            "zenoh_version": identity.zenoh_version,
            "access_control": identity.access_control,
            "tls": identity.tls,
        }

    def _judge_load(self, interval_s: float, latency_ms_p99: float | None) -> _Load:
        """The sensor path's load over the interval, handed to the overload governor; a budget
        change goes to the control worker, which re-solves the QoS."""
        processed, idle_s = self._sensor_path()
        last_processed, last_idle_s = self._last_path
        self._last_path = (processed, idle_s)
        busy = min(1.0, max(0.0, 1.0 - (idle_s - last_idle_s) / interval_s))
        change = self.governor.observe(
            LoadSample(
                interval_s=interval_s,
                processed=processed - last_processed,
                load=busy,
                latency_ms_p99=latency_ms_p99,
            )
        )
        if change is not None:
            self._on_budget(change)
        return _Load(processed, busy, latency_ms_p99)


@dataclass(frozen=True, slots=True)
class _Load:
    processed: int
    load: float
    latency_ms_p99: float | None
