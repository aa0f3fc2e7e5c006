"""The CEDDP's ingest pipeline: decode, check sequence numbers, measure, cache control, plan.

Pure logic driven by ``handle_sensor(key, payload, arrival_ns)``: the server feeds it from its
worker thread, the benchmark and unit tests call it directly. Every sample ends in exactly one
counter: decode error, cache-control discard, or passed to planning; sequence gaps are counted as
loss per writer, so ``received + lost == sent`` can be checked against the robots' own counters.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import msgspec

from arpz.ceddp.cache_control import CacheControl, CacheControlCounters, CacheSlot
from arpz.ceddp.planner import Planner, Reading
from arpz.core import keys
from arpz.core.config import LARGE_KINDS, LARGE_SAMPLE_BYTES, LARGE_TYPES
from arpz.core.messages import (
    DECODE_ERRORS,
    HELLO_DECODER,
    LARGE_SAMPLE_DECODER,
    MESSAGE_SAMPLE_DECODER,
    SAMPLE_DECODER,
    LargeSample,
    MessageSample,
    Sample,
    SensorValue,
)
from arpz.core.msgtypes import MessageTypes, same_message
from arpz.core.percentiles import Distribution
from arpz.core.protocol.wire import MAX_BATCH, MAX_SEQ, MAX_WRITE_RATE_HZ

log = logging.getLogger(__name__)

#: incarnations (writer ids) tracked per topic: a restarted robot is one more, a client inventing
#: a writer id per sample is refused past this (counted in ``over_limit``)
MAX_WRITERS_PER_TOPIC = 16


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
    #: samples refused for a seq outside 1 .. 2**63 - 1, or further ahead of the writer's last
    #: one than it can have written since (wire.MAX_WRITE_RATE_HZ): bad input, not loss
    implausible_seq: int = 0
    #: samples refused because the topic already tracks MAX_WRITERS_PER_TOPIC writer ids
    writers_over_limit: int = 0
    #: when the last sample of the topic arrived (the time base of the plausible jump)
    last_arrival_ns: int = 0
    #: samples refused undecoded for being larger than ``max_bytes``
    oversize: int = 0
    #: per writer, the highest seq the previous run of this CEDDP received (``previous_summary``)
    seen_before: dict[str, int] = field(default_factory=dict)
    #: the current writer's entry of ``seen_before`` (0: none)
    prev_high: int = 0
    #: samples with a seq the previous run already received (a restart's TRANSIENT_LOCAL
    #: catch-up): counted, and kept from the planner, never taken for new data
    repeated_from_previous_run: int = 0
    #: the size bound of this topic's samples (by its kind, once the robot announced it)
    max_bytes: int = 65_536
    #: a camera or point-cloud topic (announced so, or arriving as frames): ``LargeSample``s
    large: bool = False
    #: a typed topic's ROS 2 message type (announced, and known to this CEDDP with the same
    #: hash): its samples are ``MessageSample``s (or ``LargeSample``s of the message's bytes)
    msg_type: str | None = None
    #: the sequence state of the writer of the last sample (the hot path compares only this);
    #: other writers' states wait in ``others`` (many writers to one topic is legitimate)
    writer: str = ""
    next_seq: int = 0
    highest_seq: int = 0
    #: the same writer's share of received, lost, before_join and bytes (per incarnation
    #: reporting: the status page shows a robot's current incarnation)
    w_received: int = 0
    w_lost: int = 0
    w_before_join: int = 0
    w_bytes: int = 0
    #: other writers: (next_seq, highest_seq, received, lost, before_join, bytes)
    others: dict[str, tuple[int, int, int, int, int, int]] = field(default_factory=dict)
    #: writers whose samples are dropped (the newer of two processes running with one
    #: robot_id: ``Ingest.drop_writer``); the robot's set, shared by its topics
    dropped: set[str] = field(default_factory=set)
    #: samples dropped so, per writer
    duplicate_dropped: dict[str, int] = field(default_factory=dict)
    #: the robot's clock offset to this CEDDP's (arpz/ceddp/clock_service.py): latencies and
    #: staleness are measured on the CEDDP's clock; 0 until the robot's first estimate
    clock_offset_ns: int = 0
    #: samples received before the robot's first clock estimate (measured on its own clock)
    clock_uncorrected: int = 0
    clock_known: bool = False
    latency_ms: Distribution = field(default_factory=Distribution)
    #: how long this CEDDP held a value other than the robot's latest reading, measured once
    #: per change when the new value arrives (arrival - the robot's first read of it)
    staleness_ms: Distribution = field(default_factory=Distribution)
    #: the value the CEDDP holds now (the last one received), independent of cache control
    held: object = None
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
        max_sample_bytes: dict[str, int] | None = None,
        types: MessageTypes | None = None,
    ) -> None:
        #: the message types this CEDDP knows (the standard ones and its ``msg_paths``')
        self.types = types or MessageTypes()
        #: per robot, its typed topics' message types (those this CEDDP can decode)
        self._msg_types: dict[str, dict[str, str]] = {}
        #: announced typed topics this CEDDP cannot decode: (robot, topic) -> why
        self.types_refused: dict[tuple[str, str], str] = {}
        #: per sensor kind, and "default" for the others and for topics not yet announced
        self.max_sample_bytes = {
            "default": 65_536,
            **dict.fromkeys(LARGE_KINDS, LARGE_SAMPLE_BYTES),
            **dict.fromkeys(LARGE_TYPES, LARGE_SAMPLE_BYTES),
            **(max_sample_bytes or {}),
        }
        #: the bound of a large topic not yet announced
        self._large_limit = max(self.max_sample_bytes[kind] for kind in LARGE_KINDS)
        #: per robot, its topics announced as a large kind
        self._large: dict[str, set[str]] = {}
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
        #: (robot, topic) -> writer -> highest seq the previous run received
        self.seen_before: dict[tuple[str, str], dict[str, int]] = {}
        #: per robot, the size bound of each announced topic
        self._kinds: dict[str, dict[str, int]] = {}
        self._prefix = keys.fleet_prefix(fleet) + "/robot/"
        #: per robot, its clock offset in force (``set_clock_offset``) and its topics
        self.clock_offsets: dict[str, int] = {}
        self._robot_topics: dict[str, list[TopicMetrics]] = {}
        #: per robot, the writers whose samples are dropped (``drop_writer``)
        self._dropped: dict[str, set[str]] = {}

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
                metrics = TopicMetrics(
                    robot,
                    topic,
                    cache=self.cache_control.slot(robot, topic),
                    max_bytes=self._kinds.get(robot, {}).get(
                        topic, self.max_sample_bytes["default"]
                    ),
                    large=topic in self._large.get(robot, ()),
                    msg_type=self._msg_types.get(robot, {}).get(topic),
                    seen_before=self.seen_before.get((robot, topic), {}),
                    clock_offset_ns=self.clock_offsets.get(robot, 0),
                    clock_known=robot in self.clock_offsets,
                    dropped=self._dropped.setdefault(robot, set()),
                )
                metrics.cache.typed = metrics.msg_type is not None
                self.topics[(robot, topic)] = metrics
                self._robot_topics.setdefault(robot, []).append(metrics)
            self._by_key[key] = metrics
        return metrics

    def set_kinds(
        self,
        robot: str,
        kinds: dict[str, str],
        msg_types: Mapping[str, tuple[str, str]] | None = None,
    ) -> list[str]:
        """The robot announced its topics' kinds, and its typed topics' (message type, hash):
        bound each topic's samples by its kind's size, and decode a typed topic by its type
        (call with ``lock`` held). Topics not tracked yet get theirs when they are created.
        Returns, for each typed topic this CEDDP cannot decode, why (for the event log)."""
        limits = self.max_sample_bytes
        announced = list(kinds.items())[:256]
        typed = self._typed(robot, dict(list((msg_types or {}).items())[:256]))
        self._msg_types[robot] = typed
        self._kinds[robot] = {
            topic: limits.get(typed.get(topic, kind), limits["default"])
            for topic, kind in announced
        }
        self._large[robot] = {
            topic
            for topic, kind in announced
            if kind in LARGE_KINDS or typed.get(topic) in LARGE_TYPES
        }
        for (r, topic), metrics in self.topics.items():
            if r == robot:
                metrics.max_bytes = self._kinds[robot].get(topic, limits["default"])
                metrics.large = topic in self._large[robot]
                metrics.msg_type = typed.get(topic)
                metrics.cache.typed = metrics.msg_type is not None
        return [why for (r, _), why in self.types_refused.items() if r == robot]

    def _typed(self, robot: str, msg_types: Mapping[str, tuple[str, str]]) -> dict[str, str]:
        """The typed topics this CEDDP decodes: the type known here, with the robot's hash."""
        usable: dict[str, str] = {}
        for key in [k for k in self.types_refused if k[0] == robot]:
            del self.types_refused[key]
        for topic, (name, type_hash) in msg_types.items():
            if not self.types.known(name):
                why = (
                    f"robot {robot} topic {topic}: type {name} is unknown to this CEDDP (give it "
                    "the robots' msg_paths); its samples are refused and counted"
                )
            elif type_hash and type_hash != self.types.type_hash(name):
                why = (
                    f"robot {robot} topic {topic}: type {name} has hash {type_hash} on the "
                    f"robot and {self.types.type_hash(name)} here: the two definitions differ "
                    "(give both the same msg_paths); its samples are refused and counted"
                )
            else:
                usable[topic] = name
                continue
            self.types_refused[(robot, topic)] = why
        return usable

    def set_clock_offset(self, robot: str, offset_ns: int) -> None:
        """The robot's clock offset to this CEDDP's (call with ``lock`` held): its latencies
        and staleness from now on are measured on the CEDDP's clock. What arrived before its
        first estimate is counted in ``clock_uncorrected``."""
        self.clock_offsets[robot] = offset_ns
        for metrics in self._robot_topics.get(robot, ()):
            if not metrics.clock_known:
                metrics.clock_known = True
                metrics.clock_uncorrected = metrics.received
            metrics.clock_offset_ns = offset_ns

    def drop_writer(self, robot: str, writer: str) -> None:
        """From now on drop ``writer``'s samples of every topic of ``robot``, counted in each
        topic's ``duplicate_dropped`` (call with ``lock`` held): the newer of two processes
        running with one robot_id, whose readings would interleave with the other's. Its
        sequence state is kept aside, as any other writer's."""
        dropped = self._dropped.setdefault(robot, set())
        dropped.add(writer)
        for metrics in self._robot_topics.get(robot, ()):
            metrics.dropped = dropped
            if metrics.writer == writer:
                # its samples must never "follow" (the path that skips the checks)
                self._set_aside(metrics)
                metrics.writer = ""

    def keep_writer(self, robot: str, writer: str) -> None:
        """Count ``writer``'s samples again (call with ``lock`` held): the process it
        was dropped for stopped. The samples dropped meanwhile show as a gap in its seqs."""
        self._dropped.get(robot, set()).discard(writer)

    def robot_topics(self, robot: str) -> list[TopicMetrics]:
        """The robot's topics (call with ``lock`` held)."""
        return list(self._robot_topics.get(robot, ()))

    def clock_uncorrected(self, robot: str) -> int:
        """Samples of the robot measured on its own clock: all of them until its first clock
        estimate, then those that came before it (call with ``lock`` held)."""
        return sum(
            m.clock_uncorrected if m.clock_known else m.received
            for m in self._robot_topics.get(robot, ())
        )

    def _room_for(self, robot: str, topic: str) -> bool:
        """Per-topic state is created only for valid names within the limits, so a client
        inventing robot ids or topic names cannot make the CEDDP grow without bound."""
        try:
            keys.check_chunk(robot, what="robot id")
            keys.check_chunk(topic, what="topic")
        except keys.KeyExprError:
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

    def handle_sensor(
        self, key: str, payload: bytes, arrival_ns: int, *, large: bool = False
    ) -> None:
        """One sample on ``key``. ``large``: a camera frame or point cloud reassembled from the
        channel's fragments, which may come before the robot announced the topic's kind: the
        topic is large from then on, bounded by the largest size a large kind may have."""
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
        if large and not metrics.large:
            if metrics.robot in self._large:
                # announced as a small kind: a frame there is bad input, not a change of kind
                metrics.decode_errors += 1
                if metrics.decode_errors in (1, 10, 100) or metrics.decode_errors % 10000 == 0:
                    log.warning(
                        "frame on %s refused: the robot announced it as a small sensor (%d so far)",
                        key,
                        metrics.decode_errors,
                    )
                return
            metrics.large = True
            metrics.max_bytes = max(metrics.max_bytes, self._large_limit)
        self._ingest(metrics, key, payload, arrival_ns)

    def handle_run(self, key: str, payloads: Sequence[bytes], arrival_ns: int) -> None:
        """Samples of one writer on ``key``, in order, that arrived together (a batch the
        reliable channel delivered): the topic is looked up once, not once a sample. A sample
        that fails is logged and the run goes on; nothing else of it is lost."""
        metrics = self._by_key.get(key)
        if metrics is None:  # a new, unknown or refused key: counted a sample, as one by one
            for payload in payloads:
                self._handle_logged(key, payload, arrival_ns)
            return
        ingest = self._ingest
        for payload in payloads:
            try:
                ingest(metrics, key, payload, arrival_ns)
            except Exception:  # a bad sample or a planner bug must not lose the rest
                log.exception("ingest failed on %s", key)

    def _handle_logged(self, key: str, payload: bytes, arrival_ns: int) -> None:
        try:
            self.handle_sensor(key, payload, arrival_ns)
        except Exception:  # a bad sample or a planner bug must not lose the rest
            log.exception("ingest failed on %s", key)

    def _ingest(self, metrics: TopicMetrics, key: str, payload: bytes, arrival_ns: int) -> None:
        """One sample of a known topic: size bound, decode, sequence, latency, cache control,
        planner."""
        if len(payload) > metrics.max_bytes:
            metrics.oversize += 1
            if metrics.oversize in (1, 10, 100) or metrics.oversize % 10000 == 0:
                log.warning(
                    "sample of %d bytes on %s refused: more than %d for its kind (%d so far)",
                    len(payload),
                    key,
                    metrics.max_bytes,
                    metrics.oversize,
                )
            return
        if metrics.topic == keys.HELLO:
            self._handle_hello(metrics, payload, arrival_ns)
            return
        sample: Sample | LargeSample | MessageSample
        value: SensorValue | msgspec.Struct
        try:
            if metrics.msg_type is None:
                sample = (LARGE_SAMPLE_DECODER if metrics.large else SAMPLE_DECODER).decode(payload)
                value = sample.value
            else:
                sample = (LARGE_SAMPLE_DECODER if metrics.large else MESSAGE_SAMPLE_DECODER).decode(
                    payload
                )
                value = self.types.decode(metrics.msg_type, sample.value)
        except DECODE_ERRORS as exc:
            self._decode_error(metrics, key, payload, exc)
            return
        # the common case (same writer, next number) inlined: this runs for every sample
        seq = sample.seq
        same_writer = sample.writer is metrics.writer or sample.writer == metrics.writer
        follows = same_writer and seq == metrics.next_seq
        if not follows:
            if metrics.dropped and sample.writer in metrics.dropped:
                self._drop(metrics, sample.writer)
                return
            if not self._admissible(metrics, sample.writer, seq, arrival_ns, key):
                return
        metrics.last_arrival_ns = arrival_ns
        if same_writer:
            size = len(payload)
            metrics.received += 1
            metrics.w_received += 1
            metrics.bytes += size
            metrics.w_bytes += size
            # on the CEDDP's clock: the robot's clock offset taken out (clock_service.py)
            latency_ns = arrival_ns - sample.stamp_ns - metrics.clock_offset_ns
            metrics.latency_ms.add(latency_ns / 1e6)
            if follows:
                metrics.next_seq = seq + 1
                metrics.highest_seq = seq
            else:
                self._sequence_jump(metrics, seq)
        else:
            self._account(metrics, sample.writer, seq, sample.stamp_ns, arrival_ns, len(payload))
        if seq <= metrics.prev_high:
            metrics.repeated_from_previous_run += 1
            return
        held = metrics.held
        if held is None:
            metrics.held = value  # the first value: nothing was stale before it
        elif type(held) is not type(value) or (
            held != value and (metrics.msg_type is None or not same_message(held, value))
        ):
            # after lost samples, the CEDDP may have been stale since the oldest of them was
            # read: the robot says when that was (``since_ns``; conservative by at most the
            # acknowledgement delay)
            start_ns = (sample.since_ns if not follows else 0) or sample.changed_ns
            start_ns = (start_ns or sample.stamp_ns) + metrics.clock_offset_ns
            metrics.staleness_ms.add((arrival_ns - start_ns) / 1e6)
            metrics.held = value
        if metrics.cache.admit(value):
            self.planner.on_reading(
                Reading(
                    metrics.robot,
                    metrics.topic,
                    value,
                    sample.stamp_ns,
                    arrival_ns,
                    sample.seq,
                    sample.writer,
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
        follows = hello.writer == metrics.writer and hello.seq == metrics.next_seq
        if not follows:
            if metrics.dropped and hello.writer in metrics.dropped:
                self._drop(metrics, hello.writer)
                return
            if not self._admissible(metrics, hello.writer, hello.seq, arrival_ns, metrics.topic):
                return
        metrics.last_arrival_ns = arrival_ns
        self._account(metrics, hello.writer, hello.seq, hello.stamp_ns, arrival_ns, len(payload))
        self.planner.on_hello(metrics.robot, hello)

    @staticmethod
    def _admissible(
        metrics: TopicMetrics, writer: str, seq: int, arrival_ns: int, key: str
    ) -> bool:
        """Whether a sample that does not simply follow its writer's last one may be counted:
        its seq in range, not further ahead than the writer can have written since the topic's
        last sample, and its writer id within the per-topic bound. Refusals are bad input,
        counted and logged at 1, 10, 100 and every 10 000 (never once per sample)."""
        reason = ""
        if not 1 <= seq <= MAX_SEQ:
            reason = "seq out of range"
        elif writer == metrics.writer or writer in metrics.others:
            next_seq = metrics.next_seq if writer == metrics.writer else metrics.others[writer][0]
            silent_s = max(arrival_ns - metrics.last_arrival_ns, 0) / 1e9
            if seq - next_seq > MAX_BATCH + MAX_WRITE_RATE_HZ * silent_s:
                reason = f"seq {seq} too far past {next_seq - 1} for {silent_s:.3f} s"
        elif metrics.writer and len(metrics.others) + 1 >= MAX_WRITERS_PER_TOPIC:
            metrics.writers_over_limit += 1
            n = metrics.writers_over_limit
            if n in (1, 10, 100) or n % 10000 == 0:
                log.warning(
                    "sample on %s refused: more than %d writer ids on the topic (%d so far)",
                    key,
                    MAX_WRITERS_PER_TOPIC,
                    n,
                )
            return False
        if not reason:
            return True
        metrics.implausible_seq += 1
        n = metrics.implausible_seq
        if n in (1, 10, 100) or n % 10000 == 0:
            log.warning("sample on %s refused: %s (%d so far)", key, reason, n)
        return False

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
    def _drop(metrics: TopicMetrics, writer: str) -> None:
        count = metrics.duplicate_dropped.get(writer, 0) + 1
        metrics.duplicate_dropped[writer] = count
        if count in (1, 10, 100) or count % 10000 == 0:
            log.warning(
                "sample of %s on %s/%s dropped: another process runs with this robot_id "
                "(%d dropped so far)",
                writer,
                metrics.robot,
                metrics.topic,
                count,
            )

    @staticmethod
    def _set_aside(metrics: TopicMetrics) -> None:
        """The current writer's sequence state into ``others`` (another writer takes over)."""
        if metrics.writer:
            metrics.others[metrics.writer] = (
                metrics.next_seq,
                metrics.highest_seq,
                metrics.w_received,
                metrics.w_lost,
                metrics.w_before_join,
                metrics.w_bytes,
            )

    @staticmethod
    def _account(
        metrics: TopicMetrics, writer: str, seq: int, stamp_ns: int, arrival_ns: int, size: int
    ) -> None:
        metrics.received += 1
        metrics.bytes += size
        metrics.latency_ms.add((arrival_ns - stamp_ns - metrics.clock_offset_ns) / 1e6)
        if writer != metrics.writer:
            previous = metrics.writer
            Ingest._set_aside(metrics)
            known = metrics.others.pop(writer, None)
            metrics.writer = writer
            metrics.prev_high = metrics.seen_before.get(writer, 0)
            if known is None:
                if previous:
                    metrics.writer_changes += 1
                metrics.before_join += max(seq - 1, 0)
                metrics.next_seq = seq + 1
                metrics.highest_seq = seq
                metrics.w_received, metrics.w_lost, metrics.w_bytes = 1, 0, size
                metrics.w_before_join = max(seq - 1, 0)
                return
            (
                metrics.next_seq,
                metrics.highest_seq,
                metrics.w_received,
                metrics.w_lost,
                metrics.w_before_join,
                metrics.w_bytes,
            ) = known
        metrics.w_received += 1
        metrics.w_bytes += size
        if seq == metrics.next_seq:
            metrics.next_seq += 1
            metrics.highest_seq = max(metrics.highest_seq, seq)
        else:
            Ingest._sequence_jump(metrics, seq)

    @staticmethod
    def _sequence_jump(metrics: TopicMetrics, seq: int) -> None:
        if seq > metrics.next_seq:
            metrics.lost += seq - metrics.next_seq
            metrics.w_lost += seq - metrics.next_seq
            metrics.next_seq = seq + 1
        else:
            metrics.out_of_order += 1
        metrics.highest_seq = max(metrics.highest_seq, seq)

    @staticmethod
    def highest_seq(metrics: TopicMetrics, writer: str) -> int:
        """The highest seq received from ``writer`` on this topic (0: none)."""
        if writer == metrics.writer:
            return metrics.highest_seq
        return metrics.others.get(writer, (0, 0, 0, 0, 0, 0))[1]

    def load_previous_run(self, topics: dict[tuple[str, str], dict[str, int]]) -> None:
        """What the previous run of this CEDDP received, per topic and writer (its summary's
        ``writers``): a sample at or below that seq is counted ``repeated_from_previous_run``."""
        self.seen_before = {
            slot: dict(list(w.items())[:MAX_WRITERS_PER_TOPIC]) for slot, w in topics.items()
        }
        for slot, metrics in self.topics.items():
            metrics.seen_before = self.seen_before.get(slot, {})
            metrics.prev_high = metrics.seen_before.get(metrics.writer, 0)

    @staticmethod
    def writer_counts(metrics: TopicMetrics) -> dict[str, tuple[int, int, int]]:
        """Per writer (incarnation) of the topic: (highest seq, received, lost + before_join)."""
        counts = {w: (o[1], o[2], o[3] + o[4]) for w, o in metrics.others.items()}
        if metrics.writer:
            counts[metrics.writer] = (
                metrics.highest_seq,
                metrics.w_received,
                metrics.w_lost + metrics.w_before_join,
            )
        return counts

    @staticmethod
    def writer_bytes(metrics: TopicMetrics, writer: str) -> int:
        """The payload bytes received from ``writer`` on this topic."""
        if writer == metrics.writer:
            return metrics.w_bytes
        return metrics.others.get(writer, (0, 0, 0, 0, 0, 0))[5]

    def cache_counters(self, robot: str, topic: str) -> CacheControlCounters:
        return self.cache_control.counters.get((robot, topic), CacheControlCounters())
