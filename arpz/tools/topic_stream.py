"""Reading one topic of a running fleet for ``arpz topic echo/hz/bw/delay``, the least intrusive
way that still counts what it misses.

- A topic written through the reliable channel is read with a channel ``Reader`` (or, for camera
  frames and point clouds on ``frames/``, a ``FrameReader``), so its DATA headers, batches and
  fragments are understood and the channel's own counters (lost, retransmitted, late) come out.
  By default the reader is **BEST_EFFORT, VOLATILE**: the writers match it but never resend to it,
  a KEEP_ALL writer never waits for its acknowledgements (a slow terminal cannot fill a robot's
  history and make its writes fail), KEEP_LAST writers count no ``overwritten_unacked`` for it,
  and no history is replayed to it. Its losses are still counted from the sequence numbers.
  ``reliable=True`` asks for RELIABLE instead: the reader NACKs what it missed and the writer
  resends it, which costs the robot resends and, for KEEP_ALL writers, makes the robot's history
  wait for this reader (a stalled reader blocks the writer up to ``max_blocking_time_s`` and then
  makes its writes fail, counted as ``write_failures``).
- A topic of a ``reliability = "none"`` fleet is read with a plain Zenoh subscriber, and loss is
  counted from the payload's own ``seq`` per writer, as the CEDDP does.

Samples are queued by the reader's threads and taken by the caller's thread (``get``): nothing is
printed or decoded on a Zenoh or channel thread. A full queue drops and counts (``queue_dropped``).
"""

from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass

import msgspec

from arpz.channel import DataInfo, FrameInfo, FrameReader, Reader, ReaderStats
from arpz.core.config import LARGE_SAMPLE_BYTES
from arpz.core.messages import DECODE_ERRORS
from arpz.core.protocol.qos import QosProfile, ReliabilityPolicy
from arpz.core.transport import Handle, Transport
from arpz.tools.fleet_graph import TopicEntry

#: messages waiting for the caller; beyond, they are dropped here and counted
QUEUE_LIMIT = 100_000
#: the reader's window (KEEP_LAST depth): samples it may hold back to put them in order
DEFAULT_DEPTH = 100


@dataclass(frozen=True)
class Message:
    """One message as it arrived: ``payload`` is the arpz message (for frames: the reassembled
    ``LargeSample``); ``arrival_ns`` is this host's wall clock, ``arrival_s`` its monotonic one."""

    key: str
    payload: bytes
    arrival_ns: int
    arrival_s: float
    #: the channel writer's guid ("" for a plain publisher)
    writer: str
    #: the channel header's source stamp (None for a plain sample)
    stamp_ns: int | None
    retransmitted: bool = False
    frame: FrameInfo | None = None


def reader_qos(*, reliable: bool, depth: int = DEFAULT_DEPTH) -> QosProfile:
    """What the tool's reader requests: BEST_EFFORT (default) or RELIABLE, VOLATILE, no deadline,
    AUTOMATIC liveliness with no lease: compatible with every writer (RELIABLE only with reliable
    writers, which the caller checks) and asking nothing of any."""
    return QosProfile(
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        depth=depth,
        max_samples=max(depth, 5000),
    )


class TopicStream:
    """One topic's messages, queued for the caller; ``counters()`` are what the reader saw."""

    def __init__(self, topic: TopicEntry, description: str) -> None:
        self.topic = topic
        #: how it reads, for the user ("channel reader BEST_EFFORT KEEP_LAST 100", "plain")
        self.description = description
        self._queue: queue.Queue[Message] = queue.Queue(QUEUE_LIMIT)
        self.queue_dropped = 0
        self._lock = threading.Lock()

    def _offer(self, message: Message) -> None:
        try:
            self._queue.put_nowait(message)
        except queue.Full:
            with self._lock:
                self.queue_dropped += 1

    def get(self, timeout_s: float) -> Message | None:
        try:
            message = self._queue.get(timeout=max(timeout_s, 0.0))
        except queue.Empty:
            return None
        self._taken(message)
        return message

    def _taken(self, message: Message) -> None:
        """Bookkeeping on the caller's thread (the plain stream counts seq gaps here)."""

    def counters(self) -> dict[str, int]:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> TopicStream:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def channel_counters(stats: ReaderStats) -> dict[str, int]:
    """The channel reader's counters a user wants beside the figures (for frames: of the
    fragments)."""
    return {
        "lost": stats.lost,
        "retransmitted": stats.retransmitted,
        "late": stats.late,
        "duplicates": stats.duplicates,
        "lifespan_expired": stats.lifespan_expired,
        "incompatible": stats.incompatible,
        "plain_refused": stats.plain_refused,
    }


class ChannelStream(TopicStream):
    """A channel ``Reader`` on the topic's key."""

    def __init__(self, transport: Transport, topic: TopicEntry, qos: QosProfile) -> None:
        super().__init__(topic, f"channel reader {_describe(qos)}")
        self.reader = Reader(transport, topic.key, qos, self._on_data)

    def _on_data(self, payload: bytes, info: DataInfo) -> None:
        now_ns, now_s = time.time_ns(), time.monotonic()
        message = Message(
            info.key, payload, now_ns, now_s, info.writer, info.stamp_ns, info.retransmitted
        )
        self._offer(message)

    def counters(self) -> dict[str, int]:
        stats = self.reader.stats()
        return {
            "delivered": stats.delivered,
            **channel_counters(stats),
            "matched_writers": self.reader.matched_count,
            "queue_dropped": self.queue_dropped + stats.queue_dropped,
        }

    def close(self) -> None:
        self.reader.close()


class FrameStream(TopicStream):
    """A ``FrameReader`` on a ``frames/`` key: reassembled frames; ``lost`` and
    ``retransmitted`` count the fragment channel's samples, beside the frame counters."""

    def __init__(self, transport: Transport, topic: TopicEntry, qos: QosProfile) -> None:
        super().__init__(topic, f"frame reader {_describe(qos)} (depth in frames)")
        self.reader = FrameReader(
            transport, topic.key, qos, self._on_frame, max_frame_bytes=LARGE_SAMPLE_BYTES
        )

    def _on_frame(self, payload: bytes, info: FrameInfo) -> None:
        now_ns, now_s = time.time_ns(), time.monotonic()
        message = Message(info.key, payload, now_ns, now_s, info.writer, info.stamp_ns, frame=info)
        self._offer(message)

    def counters(self) -> dict[str, int]:
        stats = self.reader.stats()
        frames = stats.frames
        return {
            "delivered": frames.frames_delivered,
            "frames_dropped_incomplete": frames.frames_dropped_incomplete,
            "frames_dropped_over_limit": frames.frames_dropped_over_limit,
            "frames_missing": frames.frames_missing,
            "fragments_delivered": stats.channel.delivered,
            **channel_counters(stats.channel),
            "matched_writers": self.reader.matched_count,
            "queue_dropped": self.queue_dropped + stats.channel.queue_dropped,
        }

    def close(self) -> None:
        self.reader.close()


class _Head(msgspec.Struct, array_like=True, frozen=True):
    """The head every arpz data message starts with: ``[writer, seq, stamp_ns, ...]`` (msgspec
    skips the rest of the array, a camera frame's megabyte included, without copying it)."""

    writer: str
    seq: int
    stamp_ns: int


_HEAD_DECODER = msgspec.msgpack.Decoder(_Head)


def data_head(payload: bytes) -> tuple[str, int, int] | None:
    """``(writer, seq, stamp_ns)`` of an arpz data message (Sample, LargeSample, Command, Hello,
    Telemetry: msgpack arrays that start with them); None for a report (a map) or bad bytes."""
    try:
        head = _HEAD_DECODER.decode(payload)
    except DECODE_ERRORS:
        return None
    return head.writer, head.seq, head.stamp_ns


class PlainStream(TopicStream):
    """A plain Zenoh subscriber (``reliability = "none"``): loss counted from each writer's
    payload ``seq`` (a data message's second element), as the CEDDP counts it."""

    def __init__(self, transport: Transport, topic: TopicEntry) -> None:
        super().__init__(topic, "plain Zenoh subscriber (the fleet runs reliability = none)")
        self._last_seq: dict[str, int] = {}
        self.delivered = 0
        self.lost = 0
        self.out_of_order = 0
        self.channel_samples = 0
        self._handle: Handle = transport.subscribe(topic.key, self._on_sample)

    def _on_sample(self, key: str, payload: bytes, attachment: bytes | None) -> None:
        if attachment is not None:
            with self._lock:
                self.channel_samples += 1
        self._offer(Message(key, payload, time.time_ns(), time.monotonic(), "", None))

    def _taken(self, message: Message) -> None:
        self.delivered += 1
        head = data_head(message.payload)
        if head is None:
            return
        writer, seq, _ = head
        last = self._last_seq.get(writer)
        if last is not None:
            if seq > last + 1:
                self.lost += seq - last - 1
            elif seq <= last:
                self.out_of_order += 1
                return
        self._last_seq[writer] = seq

    def counters(self) -> dict[str, int]:
        with self._lock:
            dropped, headed = self.queue_dropped, self.channel_samples
        return {
            "delivered": self.delivered,
            "lost": self.lost,
            "out_of_order": self.out_of_order,
            "channel_samples": headed,
            "queue_dropped": dropped,
        }

    def close(self) -> None:
        self._handle.undeclare()  # idempotent, as the channel readers' close


def open_stream(
    transport: Transport, topic: TopicEntry, *, reliable: bool, depth: int = DEFAULT_DEPTH
) -> TopicStream:
    """The right reader for ``topic``: channel (frames or samples) or plain."""
    if not topic.reliable_channel:
        return PlainStream(transport, topic)
    if topic.large and topic.key.split("/")[-2] == "frames":
        return FrameStream(transport, topic, reader_qos(reliable=reliable, depth=1))
    return ChannelStream(transport, topic, reader_qos(reliable=reliable, depth=depth))


def _describe(qos: QosProfile) -> str:
    return f"{qos.reliability.name} {qos.durability.name} {qos.history.name} {qos.depth}"
