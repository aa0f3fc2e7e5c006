"""The CEDDP's ingest pipeline: decode, check sequence numbers, measure, cache control, plan.

Pure logic driven by ``handle_sensor(key, payload, arrival_ns)``: the server feeds it from its
worker thread, the benchmark and unit tests call it directly. Every sample ends in exactly one
counter: decode error, cache-control discard, or passed to planning; sequence gaps are counted as
loss per writer, so ``received + lost == sent`` can be checked against the robots' own counters.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field

from arpz import keys
from arpz.ceddp.cache_control import CacheControl, CacheControlCounters, CacheSlot
from arpz.ceddp.planner import Planner, Reading
from arpz.messages import DECODE_ERRORS, HELLO_DECODER, SAMPLE_DECODER
from arpz.percentiles import Distribution

log = logging.getLogger(__name__)

HELLO_TOPIC = "hello"


@dataclass
class TopicMetrics:
    """Everything the CEDDP knows about one robot topic."""

    robot: str
    topic: str
    received: int = 0
    bytes: int = 0
    decode_errors: int = 0
    #: samples missing from the sequence (gaps) of each writer
    lost: int = 0
    #: samples that arrived with a sequence number already passed (duplicate or reordered)
    out_of_order: int = 0
    #: samples a writer had sent before this CEDDP first heard it (not yet matched, or the CEDDP
    #: started late): never received, so the summary counts them in ``lost``
    before_join: int = 0
    #: writers seen on the topic beyond the first (a restarted robot is a new incarnation)
    writer_changes: int = 0
    #: the sequence state of the writer of the last sample (the hot path compares only this);
    #: other writers' states wait in ``others`` (many writers to one topic is legitimate)
    writer: str = ""
    next_seq: int = 0
    highest_seq: int = 0
    others: dict[str, tuple[int, int]] = field(default_factory=dict)
    latency_ms: Distribution = field(default_factory=Distribution)
    cache: CacheSlot = field(default_factory=CacheSlot)


@dataclass
class IngestCounters:
    unknown_keys: int = 0
    hello_decode_errors: int = 0
    #: samples on a topic or robot beyond the limits (invented names): dropped, not tracked
    over_limit: int = 0


class Ingest:
    def __init__(
        self,
        fleet: str,
        planner: Planner,
        cache_control: CacheControl,
        *,
        max_robots: int = 1000,
        max_topics_per_robot: int = 64,
    ) -> None:
        self.max_robots = max_robots
        self.max_topics_per_robot = max_topics_per_robot
        self._topics_per_robot: dict[str, int] = {}
        self.fleet = fleet
        self.planner = planner
        self.cache_control = cache_control
        self.topics: dict[tuple[str, str], TopicMetrics] = {}
        self.counters = IngestCounters()
        #: held by the worker while it processes a batch, and by readers of the metrics
        self.lock = threading.Lock()
        self._by_key: dict[str, TopicMetrics | None] = {}
        self._prefix = keys.fleet_prefix(fleet) + "/robot/"

    def metrics_for(self, key: str) -> TopicMetrics | None:
        metrics = self._by_key.get(key)
        if metrics is None and key not in self._by_key:
            parsed = keys.parse_robot_key(key) if key.startswith(self._prefix) else None
            if parsed is None or parsed[1] != "sensor" or not parsed[2]:
                self._by_key[key] = None
                return None
            robot, _, topic = parsed
            metrics = self.topics.get((robot, topic))
            if metrics is None:
                if not self._room_for(robot, topic):
                    # not cached: invented names must not grow any table, even this one
                    self.counters.over_limit += 1
                    return None
                metrics = TopicMetrics(robot, topic, cache=self.cache_control.slot(robot, topic))
                self.topics[(robot, topic)] = metrics
            self._by_key[key] = metrics
        return metrics

    def _room_for(self, robot: str, topic: str) -> bool:
        """Per-topic state is created only for valid names within the limits, so a client
        inventing robot ids or topic names cannot make the CEDDP grow without bound."""
        try:
            keys.check_chunk(robot, what="robot id")
            keys.check_chunk(topic, what="topic")
        except keys.KeyError_:
            return False
        count = self._topics_per_robot.get(robot)
        if count is None:
            if len(self._topics_per_robot) >= self.max_robots:
                return False
            count = 0
        if count >= self.max_topics_per_robot:
            return False
        self._topics_per_robot[robot] = count + 1
        return True

    def handle_sensor(self, key: str, payload: bytes, arrival_ns: int) -> None:
        over = self.counters.over_limit
        metrics = self.metrics_for(key)
        if metrics is None:
            if self.counters.over_limit != over:
                if (
                    self.counters.over_limit in (1, 10, 100)
                    or self.counters.over_limit % 10000 == 0
                ):
                    log.warning(
                        "sample on %s dropped: too many robots or topics, or an invalid "
                        "name (%d so far)",
                        key,
                        self.counters.over_limit,
                    )
                return
            self.counters.unknown_keys += 1
            if (
                self.counters.unknown_keys in (1, 10, 100)
                or self.counters.unknown_keys % 10000 == 0
            ):
                log.warning(
                    "ignoring sample on unknown key %s (%d so far)", key, self.counters.unknown_keys
                )
            return
        if metrics.topic == HELLO_TOPIC:
            self._handle_hello(metrics, payload, arrival_ns)
            return
        try:
            sample = SAMPLE_DECODER.decode(payload)
        except DECODE_ERRORS as exc:
            self._decode_error(metrics, key, payload, exc)
            return
        # the common case (same writer, next number) inlined: this runs for every sample
        seq = sample.seq
        if sample.writer is metrics.writer or sample.writer == metrics.writer:
            metrics.received += 1
            metrics.bytes += len(payload)
            metrics.latency_ms.add((arrival_ns - sample.stamp_ns) / 1e6)
            if seq == metrics.next_seq:
                metrics.next_seq = seq + 1
                metrics.highest_seq = seq
            else:
                self._sequence_jump(metrics, seq)
        else:
            self._account(metrics, sample.writer, seq, sample.stamp_ns, arrival_ns, len(payload))
        if metrics.cache.admit(sample.value):
            self.planner.on_reading(
                Reading(
                    metrics.robot,
                    metrics.topic,
                    sample.value,
                    sample.stamp_ns,
                    arrival_ns,
                    sample.seq,
                )
            )
        elif self.planner.wants_unchanged:
            self.planner.on_unchanged(metrics.robot, metrics.topic, sample.stamp_ns)

    def _handle_hello(self, metrics: TopicMetrics, payload: bytes, arrival_ns: int) -> None:
        try:
            hello = HELLO_DECODER.decode(payload)
        except DECODE_ERRORS as exc:
            self.counters.hello_decode_errors += 1
            self._decode_error(metrics, metrics.topic, payload, exc)
            return
        self._account(metrics, hello.writer, hello.seq, hello.stamp_ns, arrival_ns, len(payload))
        self.planner.on_hello(metrics.robot, hello)

    def _decode_error(
        self, metrics: TopicMetrics, key: str, payload: bytes, exc: Exception
    ) -> None:
        metrics.decode_errors += 1
        if metrics.decode_errors in (1, 10, 100) or metrics.decode_errors % 10000 == 0:
            log.warning(
                "decode error #%d on %s (%d bytes): %s",
                metrics.decode_errors,
                key,
                len(payload),
                exc,
            )

    @staticmethod
    def _account(
        metrics: TopicMetrics, writer: str, seq: int, stamp_ns: int, arrival_ns: int, size: int
    ) -> None:
        metrics.received += 1
        metrics.bytes += size
        metrics.latency_ms.add((arrival_ns - stamp_ns) / 1e6)
        if writer != metrics.writer:
            previous = metrics.writer
            if previous:
                metrics.others[previous] = (metrics.next_seq, metrics.highest_seq)
            known = metrics.others.pop(writer, None)
            metrics.writer = writer
            if known is None:
                if previous:
                    metrics.writer_changes += 1
                metrics.before_join += max(seq - 1, 0)
                metrics.next_seq = seq + 1
                metrics.highest_seq = seq
                return
            metrics.next_seq, metrics.highest_seq = known
        if seq == metrics.next_seq:
            metrics.next_seq += 1
            metrics.highest_seq = max(metrics.highest_seq, seq)
        else:
            Ingest._sequence_jump(metrics, seq)

    @staticmethod
    def _sequence_jump(metrics: TopicMetrics, seq: int) -> None:
        if seq > metrics.next_seq:
            metrics.lost += seq - metrics.next_seq
            metrics.next_seq = seq + 1
        else:
            metrics.out_of_order += 1
        metrics.highest_seq = max(metrics.highest_seq, seq)

    @staticmethod
    def highest_seq(metrics: TopicMetrics, writer: str) -> int:
        """The highest seq received from ``writer`` on this topic (0: none)."""
        if writer == metrics.writer:
            return metrics.highest_seq
        return metrics.others.get(writer, (0, 0))[1]

    def cache_counters(self, robot: str, topic: str) -> CacheControlCounters:
        return self.cache_control.counters.get((robot, topic), CacheControlCounters())
