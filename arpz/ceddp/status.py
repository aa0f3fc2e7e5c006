"""The fleet's state now, read-only: what the status page, ``/api/status`` and ``/metrics`` show.

``StatusReader.read`` copies what it needs out of the CEDDP's live state into frozen Structs and
returns them; nothing it returns is shared with the ingest, so a web request never holds a lock
longer than the copy. Counters (received, lost, bytes, the robots' own channel counters) are read
at the moment of the call, and rates are measured between reads (``RateWindow``). Figures of an
interval (latency and staleness percentiles, the CEDDP's CPU and load) come from the metrics
ticker's last frame, so a request never takes the ticker's windows away from the dashboard.
Clock offsets appear when the frame carries them (``clock_offset_ms`` / ``clock_delay_ms``),
None otherwise.

A robot's counters are its current incarnation's (the one the control worker follows): a
restarted robot starts from zero with only the topics it has now, and what its earlier
incarnations did is summed apart (``RobotStatus.previous``), never shown as live.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections import deque
from collections.abc import Callable, Hashable, Iterable
from typing import Any, Generic, NamedTuple, TypeVar

import msgspec

from arpz.ceddp.control import RobotRecord
from arpz.ceddp.ingest import Ingest, TopicMetrics
from arpz.core.config import CeddpConfig
from arpz.core.frames import MetricsFrame
from arpz.core.messages import RobotStats, TopicCounters, writer_id
from arpz.core.protocol.reader_machine import ReaderStats

#: the row of the CEDDP itself in a MetricsFrame's ``robots`` (metrics.py)
CEDDP_ROW = "ceddp"
#: the shortest span the status's rates are measured over (see RateWindow)
RATE_WINDOW_S = 2.0
K = TypeVar("K", bound=Hashable)


class TopicStatus(msgspec.Struct, frozen=True, kw_only=True):
    """One robot topic: the CEDDP's counters now, the last interval's figures, and what the
    robot reported of it (its reliable channel's side of the link)."""

    topic: str
    #: the sensor kind the robot announced (None until it did)
    kind: str | None
    received: int
    bytes: int
    #: sequence gaps plus what the writer sent before this CEDDP heard it (not the tail after
    #: the last arrival, which only the robot's final report reveals: see the summary)
    lost: int
    decode_errors: int
    cc_discarded: int
    #: seconds since the last sample arrived (None: none yet)
    last_sample_age_s: float | None
    #: received per second over the last RATE_WINDOW_S or more (None: no earlier read yet)
    rate_hz: float | None
    bytes_per_s: float | None
    latency_ms_p50: float | None
    latency_ms_p99: float | None
    staleness_ms_p99: float | None
    #: from the robot's last stats report (0 before the first)
    sent: int
    held_back: int
    retransmitted: int
    gapped: int
    deadline_missed: int
    write_failures: int
    #: reads that gave no reading (the driver raised, or its value was refused), reads longer
    #: than the period, and the last error's text ("": none)
    driver_errors: int = 0
    late_reads: int = 0
    last_driver_error: str = ""
    #: no reading for the robot's whole last reporting interval
    silent: bool = False


class PreviousIncarnations(msgspec.Struct, frozen=True, kw_only=True):
    """What a robot's earlier incarnations (before a restart, or a second process with its id)
    did, summed: not live, and never in the robot's own counters."""

    incarnations: int = 0
    received: int = 0
    lost: int = 0
    bytes: int = 0
    #: from each one's last report
    sent: int = 0
    driver_errors: int = 0


class RobotStatus(msgspec.Struct, frozen=True, kw_only=True):
    """One robot: presence, the QoS assignment in force, link quality (sums over its sensor
    topics), and its topics."""

    robot: str
    alive: bool
    joins: int
    leaves: int
    #: "channel" or "none" (None until its mode token was seen)
    mode: str | None
    cpu_percent: float | None
    #: the CEDDP QoS assignment the robot runs (epoch 0: none, its own config)
    qos_epoch: int
    qos_rate_hz: float | None
    qos_depth: int | None
    received: int
    lost: int
    #: lost / (received + lost), 0..1 (None: nothing yet)
    loss_ratio: float | None
    sent: int
    retransmitted: int
    #: samples the robot answered with GAP (a NACK came too late: lost for sure)
    gapped: int
    #: retransmitted / sent, 0..1 (None: nothing sent yet)
    retransmit_ratio: float | None
    deadline_missed: int
    rate_hz: float | None
    latency_ms_p99: float | None
    staleness_ms_p99: float | None
    last_sample_age_s: float | None
    hello_rtt_ms_p50: float | None
    clock_offset_ms: float | None
    clock_delay_ms: float | None
    incompatible_qos: list[str]
    topics: list[TopicStatus]
    #: the incarnation shown (None: none reported yet; then the counters are every writer's)
    incarnation: str | None = None
    #: sums over its topics, and the topics with no reading for its last interval
    driver_errors: int = 0
    late_reads: int = 0
    silent_sensors: list[str] = msgspec.field(default_factory=list)
    #: incarnations running beside the one shown (one robot_id in two processes), and the
    #: samples of theirs dropped
    duplicates: list[str] = msgspec.field(default_factory=list)
    duplicate_dropped: int = 0
    previous: PreviousIncarnations = msgspec.field(default_factory=PreviousIncarnations)


class ChannelStatus(msgspec.Struct, frozen=True, kw_only=True):
    """The CEDDP's sensor reader of the reliable channel (all robots together)."""

    delivered: int
    lost: int
    retransmitted: int
    nacks: int
    gaps: int
    deadline_missed: int
    matched: int


class CeddpStatus(msgspec.Struct, frozen=True, kw_only=True):
    cpu_percent: float | None
    #: share of the last interval the sensor path worked, 0..1
    ingest_load: float | None
    #: the longest a sample waited before the sensor path took it, over the last interval, ms
    #: (None: the raw path, or no interval yet)
    ingest_backlog_ms: float | None = None
    capacity_hz: float | None
    budget_hz: float | None
    processed: int
    #: None in plain mode (``reliability = "none"``)
    channel: ChannelStatus | None


class FleetStatus(msgspec.Struct, frozen=True, kw_only=True):
    fleet: str
    partition: str
    stamp_ns: int
    uptime_s: float
    #: when the interval figures were measured (0: no interval yet)
    metrics_stamp_ns: int
    ceddp: CeddpStatus
    robots: list[RobotStatus]
    #: the live views' ports (0: off): the page builds its links from them
    grpc_port: int
    rerun_web_port: int
    foxglove_port: int
    #: per live view, frames it dropped because it fell behind (never slowing ingest)
    views_dropped: dict[str, int]


class RateWindow(Generic[K]):
    """Rates from successive reads of cumulative counts: the counts now against the newest
    earlier read at least ``window_s`` old (before there is one, the oldest kept). A status
    page polling every second gets rates over the last two seconds; the metrics ticker's
    interval (``metrics_period_s``, often a fraction of a second) is too short for a person to
    read a rate from. Thread-safe: web requests read concurrently."""

    def __init__(self, window_s: float, *, keep: int = 256) -> None:
        self.window_s = window_s
        self._lock = threading.Lock()
        self._reads: deque[tuple[float, dict[K, tuple[int, int]]]] = deque(maxlen=keep)

    def rates(self, now_s: float, counts: dict[K, tuple[int, int]]) -> dict[K, tuple[float, float]]:
        """Per key, (first count, second count) per second since the base read; keys the base
        read did not have get no rate yet."""
        with self._lock:
            reads = self._reads
            while len(reads) >= 2 and reads[1][0] <= now_s - self.window_s:
                reads.popleft()
            base = reads[0] if reads else None
            reads.append((now_s, counts))
        if base is None or now_s - base[0] <= 0.0:
            return {}
        span_s = now_s - base[0]
        out = {}
        for key, (first, second) in counts.items():
            before = base[1].get(key)
            if before is not None:
                out[key] = ((first - before[0]) / span_s, (second - before[1]) / span_s)
        return out


class StatusReader:
    """Reads a ``FleetStatus`` from the CEDDP's parts; safe to call from any thread."""

    def __init__(
        self,
        config: CeddpConfig,
        ingest: Ingest,
        robots: dict[str, RobotRecord],
        last_frame: Callable[[], MetricsFrame | None],
        *,
        processed: Callable[[], int],
        channel: Callable[[], ReaderStats | None],
        views_dropped: Callable[[], dict[str, int]] = dict,
    ) -> None:
        self.config = config
        self.ingest = ingest
        self.robots = robots
        self._last_frame = last_frame
        self._processed = processed
        self._channel = channel
        self._views_dropped = views_dropped
        self._started_ns = time.time_ns()
        #: per (robot, topic, incarnation): a restart's counts start again from zero
        self._rates: RateWindow[tuple[str, str, str]] = RateWindow(RATE_WINDOW_S)

    def kind_of(self, robot: str, topic: str) -> str | None:
        """The sensor kind ``robot`` announced for ``topic`` (None: not announced yet)."""
        with self.ingest.lock:
            return _kind(self.robots.get(robot), topic)

    def read(self) -> FleetStatus:
        now_ns = time.time_ns()
        frame = self._last_frame()
        frame_topics = frame.topics if frame is not None else {}
        frame_robots = frame.robots if frame is not None else {}
        ingest = self.ingest
        with ingest.lock:  # only copies under the lock: the ingest waits for nothing else
            records = {name: _copy(record) for name, record in self.robots.items()}
            copied = [
                _Taken(
                    slot,
                    m.received,
                    m.bytes,
                    m.lost + m.before_join,
                    m.decode_errors,
                    ingest.cache_counters(*slot).hits,
                    m.last_arrival_ns,
                    _writers(m),
                    sum(m.duplicate_dropped.values()),
                )
                for slot, m in ingest.topics.items()
                if slot[1] != "hello"
            ]
        by_robot: dict[str, list[_Taken]] = {}
        for one in copied:
            by_robot.setdefault(one.slot[0], []).append(one)
        rows: dict[str, list[tuple[str, _Counts, _Taken | None]]] = {}
        previous: dict[str, PreviousIncarnations] = {}
        counts: dict[tuple[str, str, str], tuple[int, int]] = {}
        for robot in set(by_robot) | set(records):
            record = records.get(robot)
            current = record.incarnation if record is not None else ""
            mine = {t.slot[1]: t for t in by_robot.get(robot, [])}
            rows[robot] = []
            for topic in sorted(_topics_of(robot, record, mine)):
                found = mine.get(topic)
                own = _own_counts(found, record, current)
                rows[robot].append((topic, own, found))
                counts[(robot, topic, current)] = (own.received, own.bytes)
            if record is not None and current:
                previous[robot] = _previous(robot, record, by_robot.get(robot, []))
        rates = self._rates.rates(time.monotonic(), counts)
        per_robot: dict[str, list[TopicStatus]] = {}
        for robot, topic_rows in sorted(rows.items()):
            record = records.get(robot)
            stats = _followed_stats(record)
            current = record.incarnation if record is not None else ""
            for topic, own, taken in topic_rows:
                counters = stats.topics.get(topic) if stats is not None else None
                row = frame_topics.get((robot, topic), {})
                rate_hz, bytes_per_s = rates.get((robot, topic, current), (None, None))
                last_ns = taken.last_arrival_ns if taken is not None else 0
                per_robot.setdefault(robot, []).append(
                    TopicStatus(
                        topic=topic,
                        kind=_kind(record, topic),
                        received=own.received,
                        bytes=own.bytes,
                        lost=own.lost,
                        decode_errors=own.decode_errors,
                        cc_discarded=own.cc_discarded,
                        last_sample_age_s=(
                            round(max(now_ns - last_ns, 0) / 1e9, 3) if last_ns else None
                        ),
                        rate_hz=rate_hz,
                        bytes_per_s=bytes_per_s,
                        latency_ms_p50=row.get("latency_ms_p50"),
                        latency_ms_p99=row.get("latency_ms_p99"),
                        staleness_ms_p99=row.get("staleness_ms_p99"),
                        silent=stats is not None and topic in stats.silent_sensors,
                        **_robot_side(counters),
                    )
                )
        names = sorted((set(per_robot) | set(records)) - {CEDDP_ROW})
        robots = [
            _robot_status(
                name,
                records.get(name, RobotRecord()),
                per_robot.get(name, []),
                frame_robots.get(name, {}),
                previous.get(name, PreviousIncarnations()),
                sum(t.dropped for t in by_robot.get(name, [])),
            )
            for name in names
        ]
        ceddp_row = frame_robots.get(CEDDP_ROW, {})
        reader = self._channel()
        cfg = self.config
        return FleetStatus(
            fleet=cfg.fleet,
            partition=cfg.partition,
            stamp_ns=now_ns,
            uptime_s=round((now_ns - self._started_ns) / 1e9, 3),
            metrics_stamp_ns=frame.stamp_ns if frame is not None else 0,
            ceddp=CeddpStatus(
                cpu_percent=ceddp_row.get("cpu_percent"),
                ingest_load=ceddp_row.get("ingest_load"),
                ingest_backlog_ms=ceddp_row.get("ingest_backlog_ms"),
                capacity_hz=ceddp_row.get("capacity_hz"),
                budget_hz=ceddp_row.get("budget_hz"),
                processed=self._processed(),
                channel=(
                    ChannelStatus(
                        delivered=reader.delivered,
                        lost=reader.lost,
                        retransmitted=reader.retransmitted,
                        nacks=reader.nacks,
                        gaps=reader.gaps,
                        deadline_missed=reader.deadline_missed,
                        matched=reader.matched,
                    )
                    if reader is not None
                    else None
                ),
            ),
            robots=robots,
            grpc_port=cfg.grpc_port,
            rerun_web_port=cfg.rerun_web_port,
            foxglove_port=cfg.foxglove_port,
            views_dropped=self._views_dropped(),
        )


class _Taken(NamedTuple):
    """One topic's counters, copied under the ingest lock."""

    slot: tuple[str, str]
    received: int
    bytes: int
    lost: int
    decode_errors: int
    cc_hits: int
    last_arrival_ns: int
    #: per writer: (received, lost + before_join, bytes)
    writers: dict[str, tuple[int, int, int]]
    #: samples of a second process with the robot's id, dropped
    dropped: int


class _Counts(NamedTuple):
    received: int
    bytes: int
    lost: int
    decode_errors: int
    cc_discarded: int


def _writers(m: TopicMetrics) -> dict[str, tuple[int, int, int]]:
    return {
        w: (received, lost, Ingest.writer_bytes(m, w))
        for w, (_, received, lost) in Ingest.writer_counts(m).items()
    }


def _copy(record: RobotRecord) -> RobotRecord:
    """The fields the status reads, taken under the lock (the record itself keeps changing)."""
    now = time.monotonic()
    return RobotRecord(
        alive=record.alive,
        joins=record.joins,
        leaves=record.leaves,
        stats=record.stats,
        announce=record.announce,
        mode=record.mode,
        incompatible=list(record.incompatible),
        incarnation=record.incarnation,
        incarnations=dict(record.incarnations),
        seen=dict(record.seen),
        # only the live ones (a copy: the originals keep changing)
        duplicates={
            name: dataclasses.replace(d) for name, d in record.duplicates.items() if d.live(now)
        },
        baselines=dict(record.baselines),
    )


def _followed_stats(record: RobotRecord | None) -> RobotStats | None:
    """The last report of the incarnation followed (None: none yet)."""
    if record is None or record.stats is None:
        return None
    if record.incarnation and record.stats.incarnation != record.incarnation:
        return None
    return record.stats


def _topics_of(robot: str, record: RobotRecord | None, arrived: dict[str, _Taken]) -> set[str]:
    """The robot's topics now: those its current incarnation's samples came on, and those it
    reports that never sent anything (a sensor whose driver fails: no sample tells of it).
    Before any report, every topic that arrived."""
    current = record.incarnation if record is not None else ""
    if record is None or not current:
        return set(arrived)
    own = writer_id(robot, current)
    names = {t for t, taken in arrived.items() if own in taken.writers}
    stats = _followed_stats(record)
    if stats is not None:
        names.update(t for t, c in stats.topics.items() if c.sent == 0 and t != "hello")
    return names


def _own_counts(taken: _Taken | None, record: RobotRecord | None, current: str) -> _Counts:
    """A topic's counters for the incarnation followed (every writer's before it reported)."""
    if taken is None:
        return _Counts(0, 0, 0, 0, 0)
    if record is None or not current:
        return _Counts(taken.received, taken.bytes, taken.lost, taken.decode_errors, taken.cc_hits)
    received, lost, size = taken.writers.get(writer_id(taken.slot[0], current), (0, 0, 0))
    errors, hits = record.baselines.get(taken.slot[1], (0, 0))
    return _Counts(
        received, size, lost, max(taken.decode_errors - errors, 0), max(taken.cc_hits - hits, 0)
    )


def _previous(robot: str, record: RobotRecord, topics: list[_Taken]) -> PreviousIncarnations:
    """What the robot's other incarnations did, summed."""
    current = writer_id(robot, record.incarnation)
    received = lost = size = 0
    names = (set(record.seen) | set(record.incarnations)) - {record.incarnation}
    for taken in topics:
        for writer, (got, missing, nbytes) in taken.writers.items():
            if writer != current:
                names.add(writer.rpartition(":")[2])
                received, lost, size = received + got, lost + missing, size + nbytes
    others = [s for name, s in record.incarnations.items() if name != record.incarnation]
    return PreviousIncarnations(
        incarnations=len(names),
        received=received,
        lost=lost,
        bytes=size,
        sent=sum(c.sent for s in others for t, c in s.topics.items() if t != "hello"),
        driver_errors=sum(c.driver_errors for s in others for c in s.topics.values()),
    )


def _kind(record: RobotRecord | None, topic: str) -> str | None:
    if record is None or record.announce is None:
        return None
    for info in record.announce.sensors:
        if info.topic == topic:
            return info.kind
    return None


def _robot_side(counters: TopicCounters | None) -> dict[str, Any]:
    c = counters or TopicCounters()
    return {
        "sent": c.sent,
        "held_back": c.held_back,
        "retransmitted": c.retransmitted,
        "gapped": c.gapped,
        "deadline_missed": c.deadline_missed,
        "write_failures": c.write_failures,
        "driver_errors": c.driver_errors,
        "late_reads": c.late_reads,
        "last_driver_error": c.last_driver_error,
    }


def _robot_status(
    name: str,
    record: RobotRecord,
    topics: list[TopicStatus],
    row: dict[str, float],
    previous: PreviousIncarnations,
    dropped: int,
) -> RobotStatus:
    stats = _followed_stats(record)
    received = sum(t.received for t in topics)
    lost = sum(t.lost for t in topics)
    sent = sum(t.sent for t in topics)
    retransmitted = sum(t.retransmitted for t in topics)
    rates = [t.rate_hz for t in topics if t.rate_hz is not None]
    ages = [t.last_sample_age_s for t in topics if t.last_sample_age_s is not None]
    return RobotStatus(
        robot=name,
        alive=record.alive,
        joins=record.joins,
        leaves=record.leaves,
        mode=record.mode,
        cpu_percent=stats.cpu_percent if stats is not None else None,
        qos_epoch=stats.qos_epoch if stats is not None else 0,
        qos_rate_hz=stats.qos_rate_hz if stats is not None else None,
        qos_depth=stats.qos_depth if stats is not None else None,
        received=received,
        lost=lost,
        loss_ratio=lost / (received + lost) if received + lost else None,
        sent=sent,
        retransmitted=retransmitted,
        gapped=sum(t.gapped for t in topics),
        retransmit_ratio=retransmitted / sent if sent else None,
        deadline_missed=sum(t.deadline_missed for t in topics),
        rate_hz=sum(rates) if rates else None,
        latency_ms_p99=_worst(t.latency_ms_p99 for t in topics),
        staleness_ms_p99=_worst(t.staleness_ms_p99 for t in topics),
        last_sample_age_s=min(ages) if ages else None,
        hello_rtt_ms_p50=row.get("hello_rtt_ms_p50"),
        clock_offset_ms=row.get("clock_offset_ms"),
        clock_delay_ms=row.get("clock_delay_ms"),
        incompatible_qos=record.incompatible
        + [f"(robot side) {line}" for line in (stats.incompatible_qos if stats else [])],
        topics=topics,
        incarnation=record.incarnation or None,
        driver_errors=sum(t.driver_errors for t in topics),
        late_reads=sum(t.late_reads for t in topics),
        silent_sensors=[t.topic for t in topics if t.silent],
        duplicates=sorted(record.duplicates),
        duplicate_dropped=dropped,
        previous=previous,
    )


def _worst(values: Iterable[float | None]) -> float | None:
    """The largest of the topics' figures (a robot is as late as its latest topic)."""
    present = [v for v in values if v is not None]
    return max(present) if present else None
