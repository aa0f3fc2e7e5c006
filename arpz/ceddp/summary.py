"""The CEDDP's summary: what each robot says it did, reconciled with what arrived here.

Pure functions over the ingest's per-topic metrics and the robots' own reports. The identities
they make checkable (and that the demo, the tests and the experiments check) are, per topic:
``produced == sent + held_back + write_failures + driver_errors`` (the robot's side: every read
of a driver is produced, and a read that gave no reading is a driver error) and
``sent == received + lost`` (the network's side), where ``lost`` counts every sample that did not
arrive, whatever the cause: sequence gaps, the tail after the last arrival, and what a writer sent
before this CEDDP was listening (and, for a second process running with the robot's id, what was
dropped: ``duplicate_dropped`` says how many of them).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import msgspec

from arpz.ceddp.downlink import DownlinkCounters
from arpz.ceddp.ingest import Ingest, TopicMetrics
from arpz.ceddp.qos_control import QosController
from arpz.core.messages import RobotStats, writer_id
from arpz.core.percentiles import Distribution, LogHistogram, window_max

#: per-robot totals: the sum of these over the robot's sensor topics (not the Hello probe)
TOTALS = (
    "produced",
    "sent",
    "held_back",
    "write_failures",
    "driver_errors",
    "late_reads",
    "frames_skipped",
    "late_periods",
    "retransmitted",
    "history_offered",
    "heartbeats",
    "received",
    "cc_discarded",
    "cc_passed",
    "lost",
    "decode_errors",
    "implausible_seq",
    "implausible_lost",
    "duplicate_dropped",
)


@dataclass(frozen=True)
class RobotReport:
    """What the CEDDP knows of a robot besides its topics."""

    alive: bool
    joins: int
    leaves: int
    control_decode_errors: int
    stats: RobotStats | None
    #: INCOMPATIBLE_QOS lines; the robot's data is refused while there are any
    incompatible: list[str] = field(default_factory=list)
    #: samples refused per key because the robot's mode disagrees with the CEDDP's
    refused: dict[str, int] = field(default_factory=dict)
    #: command name -> what the CEDDP wrote to this robot
    downlink: dict[str, DownlinkCounters] = field(default_factory=dict)
    #: the last report of each incarnation (a restarted robot is a new one), oldest first
    incarnations: dict[str, RobotStats] = field(default_factory=dict)
    #: the robot's clock section (``ClockWatch.summary``; None: no clock watch)
    clock: dict[str, Any] | None = None
    #: how long (s) each time the robot was unreachable and came back as the same incarnation
    outages: list[float] = field(default_factory=list)
    #: the incarnation the CEDDP follows ("": none reported)
    incarnation: str = ""
    #: incarnations found running beside it (one robot_id in two processes): whether each runs
    #: still, how long ago it was found, how many of its reports were ignored
    duplicates: dict[str, dict[str, Any]] = field(default_factory=dict)


def incarnation_summary(
    ingest: Ingest, robot: str, incarnations: dict[str, RobotStats]
) -> dict[str, dict[str, Any]]:
    """Per incarnation of the robot: what it says it sent and what arrived from its writer, so
    that a restart never merges two runs' counts. ``reconciled``: sent == received + lost once
    the incarnation's final report came (call with ``ingest.lock`` held)."""
    rows: dict[str, dict[str, Any]] = {}
    for incarnation, stats in incarnations.items():
        writer = writer_id(robot, incarnation)
        sent = received = lost = dropped = 0
        for topic, counters in stats.topics.items():
            if topic == "hello":
                continue
            sent += counters.sent
            m = ingest.topics.get((robot, topic))
            highest, got, missing = (
                Ingest.writer_counts(m).get(writer, (0, 0, 0)) if m else (0, 0, 0)
            )
            received += got
            # what was dropped (a second process's samples) never counted as received: it is
            # in the seqs past ``highest``, so in the tail, or a gap once its turn came
            dropped += m.duplicate_dropped.get(writer, 0) if m else 0
            tail = max(counters.last_seq - highest, 0) if stats.final else 0
            lost += missing + tail
        rows[incarnation] = {
            "final": stats.final,
            "started_ns": stats.started_ns,
            "sent": sent,
            "received": received,
            "lost": lost,
            # of lost: dropped because another process ran with this robot_id
            "duplicate_dropped": dropped,
            "reconciled": (sent == received + lost) if stats.final else None,
        }
    return rows


class Samples:
    """A topic's latency or staleness figures for the summary, taken in two steps: under the
    ingest lock only its window is drained (a list swap); folding the window into the whole-run
    histogram and copying it come when ``histogram`` is first called, after the lock is
    released.

    Why: with 50 robots at 38 000 samples/s the periodic summary took 60-210 ms of wall time
    for 21-42 ms of CPU, and the fleet's p99 latency was 35-49 ms with it every 5 s against
    15 ms without (issue 17). Taking only the windows under the lock cut a robot's hold from
    0.6 to 0.2 ms (stop 34, benchmarks/RESULTS.md; ``python
    benchmarks/investigations/summary_stall.py`` prints
    today's hold)."""

    def __init__(self, distribution: Distribution) -> None:
        self._distribution = distribution
        self._window: list[float] | None = distribution.drain_window()
        self._histogram: LogHistogram | None = None
        #: the largest value so far, the window's included (a few hundred values at most)
        self.max = distribution.max
        top = window_max(self._window)
        if top is not None:
            self.max = top if self.max is None else max(self.max, top)

    def histogram(self) -> LogHistogram:
        if self._histogram is None:
            if self._window is not None:
                self._distribution.fold_window(self._window)
                self._window = None
            self._histogram = self._distribution.folded()
        return self._histogram


class Deferred:
    """One percentile of a topic's (or a robot's topics' pooled) ``Samples``, computed when
    ``resolve`` reads it, after the ingest lock is released. Computed under it, a robot's
    summary held every robot's samples back about 10 ms (percentiles of 20 000-value
    reservoirs, before the histograms), once per robot every ``summary_period_s``: the p99
    latency of a 10-robot fleet at 100 Hz was 20-23 ms with the periodic summary and 3.4 ms
    without it (issue 17)."""

    def __init__(self, sources: list[Samples], qs: tuple[float, ...], q: float, shared: list[Any]):
        self._sources, self._qs, self._q, self._shared = sources, qs, q, shared

    def value(self) -> float | None:
        if not self._shared:  # the figures of the histograms pooled, when first read
            self._shared.extend(_pooled(self._sources).quantiles(self._qs))
        result: float | None = self._shared[self._qs.index(self._q)]
        return result


def _pooled(sources: list[Samples]) -> LogHistogram:
    if len(sources) == 1:
        return sources[0].histogram()
    return LogHistogram.pooled([source.histogram() for source in sources])


def _figures(sources: list[Samples], qs: tuple[float, ...], defer: bool) -> list[Any]:
    """Percentiles of the sources' values pooled; with ``defer``, taken, pooled and computed at
    ``resolve``, outside the ingest lock."""
    if not sources:
        return [None] * len(qs)
    if not defer:
        return _pooled(sources).quantiles(qs)
    shared: list[Any] = []
    return [Deferred(sources, qs, q, shared) for q in qs]


#: the keys of a robot's row, and of each of its topics' rows, that ``defer`` leaves Deferred
DEFERRED_KEYS = ("latency_ms_p50", "latency_ms_p99", "staleness_ms_p50", "staleness_ms_p99")


def resolve(row: dict[str, Any]) -> dict[str, Any]:
    """A robot's row (``robot_summary``) with its ``Deferred`` figures, and its topics', replaced
    by their values in place (call without the ingest lock). Only the keys in ``DEFERRED_KEYS``
    are visited: walking every value of 400 topics' rows was a third of a 50-robot summary."""
    for target in (row, *row.get("topics", {}).values()):
        for key in DEFERRED_KEYS:
            value = target.get(key)
            if isinstance(value, Deferred):
                target[key] = value.value()
    return row


def topic_summary(
    ingest: Ingest,
    m: TopicMetrics,
    stats: RobotStats | None,
    *,
    defer: bool = False,
    samples: tuple[Samples, Samples] | None = None,
) -> dict[str, Any]:
    """Call with ``ingest.lock`` held; ``defer``: percentiles as ``Deferred`` (see ``resolve``);
    ``samples``: the topic's latency and staleness samples, when the caller already took them."""
    cc = ingest.cache_counters(m.robot, m.topic)
    counters = stats.topics.get(m.topic) if stats else None
    tail_lost = 0
    lost = m.lost + m.before_join
    excess = 0
    if stats is not None and stats.final and counters is not None:
        # samples sent after the last one that arrived: invisible as a gap, but lost
        last = Ingest.highest_seq(m, writer_id(m.robot, stats.incarnation))
        tail_lost = max(counters.last_seq - last, 0)
        lost += tail_lost
        if not m.writer_changes:
            # never more lost than the robot sent and we did not receive: the rest was claimed
            # by seqs the robot never wrote (its counters are the truth for one incarnation)
            excess = max(lost - max(counters.sent - m.received, 0), 0)
            lost -= excess
    latency, staleness = samples or (Samples(m.latency_ms), Samples(m.staleness_ms))
    latency_p50, latency_p99 = _figures([latency], (50, 99), defer)
    staleness_p50, staleness_p99 = _figures([staleness], (50, 99), defer)
    return {
        "produced": counters.produced if counters else 0,
        "sent": counters.sent if counters else 0,
        "held_back": counters.held_back if counters else 0,
        "write_failures": counters.write_failures if counters else 0,
        # reads that gave no reading (the driver raised, or its value was refused)
        "driver_errors": counters.driver_errors if counters else 0,
        "driver_exceptions": counters.driver_exceptions if counters else 0,
        "values_refused": counters.values_refused if counters else 0,
        "last_driver_error": counters.last_driver_error if counters else "",
        # reads that took longer than the sensor's period (sent all the same)
        "late_reads": counters.late_reads if counters else 0,
        "silent": bool(stats and m.topic in stats.silent_sensors),
        # of write_failures: a camera's frames replaced by newer ones while its link was busy
        "frames_skipped": counters.frames_skipped if counters else 0,
        # sensing periods the robot's scheduler ran late and skipped
        "late_periods": counters.late_periods if counters else 0,
        "retransmitted": counters.retransmitted if counters else 0,
        "history_offered": counters.history_offered if counters else 0,
        "heartbeats": counters.heartbeats if counters else 0,
        "gapped": counters.gapped if counters else 0,
        "overwritten_unacked": counters.overwritten_unacked if counters else 0,
        "received": m.received,
        "cc_discarded": cc.hits,
        "cc_passed": cc.misses,
        "lost": lost,
        "implausible_lost": excess,
        "implausible_seq": m.implausible_seq,
        # samples of a second process with the robot's id, dropped (counted in ``lost`` of
        # its incarnation)
        "duplicate_dropped": sum(m.duplicate_dropped.values()),
        "writers_over_limit": m.writers_over_limit,
        "oversize": m.oversize,
        "repeated_from_previous_run": m.repeated_from_previous_run,
        # highest seq received per writer: what the next run's ``previous_summary`` reads
        "writers": {w: c[0] for w, c in Ingest.writer_counts(m).items()},
        "out_of_order": m.out_of_order,
        "writer_changes": m.writer_changes,
        "before_join": m.before_join,
        "decode_errors": m.decode_errors,
        "latency_ms_p50": latency_p50,
        "latency_ms_p99": latency_p99,
        "latency_ms_max": latency.max,
        "staleness_ms_p50": staleness_p50,
        "staleness_ms_p99": staleness_p99,
        "staleness_ms_max": staleness.max,
        "cache_forgets": counters.cache_forgets if counters else 0,
    }


def downlink_summary(
    downlink: dict[str, DownlinkCounters], stats: RobotStats | None
) -> dict[str, dict[str, Any]]:
    """Per command key, the CEDDP's writer reconciled with the robot's reader.

    The robot reports, for the CEDDP's writer (this incarnation's), the range of seqs its reader
    accounted for and how many of them were delivered, declared lost or dropped past their
    lifespan (``this_writer``; the totals count every writer it had); everything written outside
    that range is ``before_match`` (written before the robot's reader matched) or
    ``after_robot_stopped`` (in flight when the robot closed its reader). ``reconciled``: the
    robot's delivered + lost + expired equals the range, and the range lies within what the CEDDP
    wrote. It is None while the robot has not sent its final report, and for a plain-put
    downlink (``channel`` false: ``plain_downlink``), which has no channel to reconcile.
    """
    rows: dict[str, dict[str, Any]] = {}
    for name, c in sorted(downlink.items()):
        inbound = stats.inbound.get(f"cmd/{name}") if stats else None
        row: dict[str, Any] = {
            "written": c.written,
            "unmatched": c.unmatched,
            "refused": c.refused,
            "write_failures": c.write_failures,
            "gapped": c.gapped,
            "retransmitted": c.retransmitted,
            "delivered": inbound.delivered if inbound else 0,
            "lost": inbound.lost if inbound else 0,
            "lifespan_expired": inbound.lifespan_expired if inbound else 0,
            "channel": bool(c.guid),
            "reconciled": None,
        }
        span = inbound.writers.get(c.guid) if inbound and c.guid else None
        if span is not None and len(span) == 5 and stats is not None and stats.final:
            start, through, delivered, lost, expired = span
            row["this_writer"] = {"delivered": delivered, "lost": lost, "lifespan_expired": expired}
            row["before_match"] = start - 1
            row["after_robot_stopped"] = max(c.last_seq - through, 0)
            row["reconciled"] = (
                delivered + lost + expired == through - start + 1 and through <= c.last_seq
            )
        rows[name] = row
    return rows


def robot_summary(
    ingest: Ingest, robot: str, report: RobotReport, *, defer: bool = False
) -> dict[str, Any]:
    """Call with ``ingest.lock`` held; ``defer``: percentiles as ``Deferred`` (see ``resolve``)."""
    stats = report.stats
    mine = sorted((t, m) for (r, t), m in ingest.topics.items() if r == robot)
    if stats is not None:
        # a sensor that never sent anything (its driver failing) has no samples here, but has
        # its row (not a topic another CEDDP of the mesh ingests: its rows are that one's)
        arrived = {t for t, _ in mine}
        mine = sorted(
            mine
            + [
                (t, TopicMetrics(robot, t))
                for t, c in stats.topics.items()
                if t not in arrived and t != "hello" and c.sent == 0 and c.produced > 0
            ],
            key=lambda pair: pair[0],
        )
    # each topic's samples taken once, for its own figures and the robot's pooled ones
    samples = {t: (Samples(m.latency_ms), Samples(m.staleness_ms)) for t, m in mine}
    topics = {
        topic: topic_summary(ingest, m, stats, defer=defer, samples=samples[topic])
        for topic, m in mine
    }
    sensors = [row for topic, row in topics.items() if topic != "hello"]
    latencies = [samples[t][0] for t, _ in mine if t != "hello"]
    latency_p50, latency_p99 = _figures(
        [samples[t][0] for t, _ in mine if t != "hello"], (50, 99), defer
    )
    (staleness_p99,) = _figures([samples[t][1] for t, _ in mine if t != "hello"], (99,), defer)
    return {
        "alive": report.alive,
        "versions": {
            "arpz": stats.arpz_version if stats else "",
            "zenoh": stats.zenoh_version if stats else "",
        },
        "control_decode_errors": report.control_decode_errors,
        "joins": report.joins,
        "leaves": report.leaves,
        "outages_s": [round(d, 3) for d in report.outages],
        "final_stats": bool(stats and stats.final),
        # the incarnation followed (its report is the one above), and any second process
        # found running with this robot_id (its samples dropped)
        "incarnation": report.incarnation,
        "duplicates": dict(report.duplicates),
        "silent_sensors": list(stats.silent_sensors) if stats else [],
        **{key: sum(row[key] for row in sensors) for key in TOTALS},
        "latency_ms_p50": latency_p50,
        "latency_ms_p99": latency_p99,
        "latency_ms_max": max((d.max for d in latencies if d.max is not None), default=None),
        # latency and staleness on the CEDDP's clock (the robot's offset taken out), or not
        "clock_corrected": bool(report.clock and report.clock["corrected"]),
        "clock": report.clock,
        "cpu_percent": stats.cpu_percent if stats else None,
        "hello": msgspec.to_builtins(stats.hello) if stats and stats.hello else None,
        "staleness_ms_p99": staleness_p99,
        "incompatible_qos": list(report.incompatible)
        + [f"(robot side) {line}" for line in (stats.incompatible_qos if stats else [])],
        "refused": sum(report.refused.values()),
        "downlink": downlink_summary(report.downlink, stats),
        "commands_expired": stats.commands_expired if stats else 0,
        "watchdog_stops": dict(stats.watchdog_stops) if stats else {},
        "incarnations": incarnation_summary(ingest, robot, report.incarnations),
        "topics": topics,
    }


def qos_summary(qos: QosController) -> dict[str, Any]:
    return {
        "assignments": [msgspec.to_builtins(m) for m in qos.history],
        "acks": {robot: msgspec.to_builtins(a) for robot, a in qos.acks.items()},
        "refusals": [msgspec.to_builtins(a) for a in qos.refusals],
        "errors": list(qos.errors),
        "mode": qos.config.mode,
        "links": qos.links_summary(),
    }


def previous_run(summary: dict[str, Any]) -> dict[tuple[str, str], dict[str, int]]:
    """Per (robot, topic), the highest seq each writer had delivered to the run that wrote
    ``summary`` (malformed entries are skipped: a summary is input like any other)."""
    seen: dict[tuple[str, str], dict[str, int]] = {}
    robots = summary.get("robots")
    if not isinstance(robots, dict):
        return seen
    for robot, row in robots.items():
        topics = row.get("topics") if isinstance(row, dict) else None
        if not isinstance(topics, dict):
            continue
        for topic, t in topics.items():
            writers = t.get("writers") if isinstance(t, dict) else None
            if isinstance(writers, dict):
                seen[(str(robot), str(topic))] = {
                    str(w): int(h) for w, h in writers.items() if isinstance(h, int) and h > 0
                }
    return seen
