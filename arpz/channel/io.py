"""Both ends of one key, in either direction: a reliable-channel endpoint, or plain Zenoh.

Robots and the CEDDP write every key through an ``Outlet`` and read every key through an
``Inlet``. With a profile each is an ``arpz.channel`` ``Writer`` / ``Reader`` (heartbeats,
ACKNACK recovery, bounded history, deadline, lifespan); with ``None`` (``reliability = "none"``,
asked for in the config) each is a plain Zenoh publisher / subscriber, and the receiver counts
loss from the payload's sequence numbers. The payload on the key is the same either way, so a
plain Zenoh client still decodes it.

A pair that disagrees (one side plain, the other through the channel) never loses data silently:
a channel ``Inlet`` refuses plain samples and a plain ``Inlet`` refuses samples that carry a
channel header; both count the refusals per key and report the pair as INCOMPATIBLE_QOS once.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from typing import Protocol

from arpz.channel import (
    PLAIN_PEER,
    FrameWriter,
    HistoryFullError,
    IncompatibleQosStatus,
    MessageLostStatus,
    QosPolicyKind,
    QosProfile,
    Reader,
    ReaderEventCallbacks,
    ReaderStats,
    Writer,
    WriterStats,
)
from arpz.core.protocol.fragments import DEFAULT_FRAGMENT_BYTES, FragmentError
from arpz.core.transport import Handle, Publisher, Transport

log = logging.getLogger(__name__)

#: ``IncompatibleQosStatus.peer`` prefix when a plain Inlet saw a channel-headed sample
CHANNEL_PEER = "channel:"


def writer_totals(stats: WriterStats | None, write_failures: int) -> dict[str, int]:
    """The channel counters a sender reports per key (zeros without the channel)."""
    return {
        "retransmitted": stats.retransmitted if stats else 0,
        "history_offered": stats.history_offered if stats else 0,
        "heartbeats": stats.heartbeats if stats else 0,
        "gapped": stats.lost if stats else 0,
        "overwritten_unacked": stats.overwritten_unacked if stats else 0,
        "deadline_missed": stats.deadline_missed if stats else 0,
        "lifespan_expired": stats.lifespan_expired if stats else 0,
        "write_failures": write_failures,
    }


class Outlet:
    """Where one key's messages go: a reliable-channel ``Writer`` or a plain publisher.

    A QoS assignment changes the depth and the offered deadline of the writer in place (same
    guid, history and matches). ``block=False`` (the default here): a stalled receiver never
    stalls the writing thread; the channel recovers or reports what Zenoh drops.
    """

    def __init__(
        self,
        transport: Transport,
        key: str,
        qos: QosProfile | None,
        *,
        block: bool = False,
        express: bool = False,
    ) -> None:
        self.transport = transport
        self.key = key
        self.writer: Writer | None = (
            Writer(transport, key, qos, block=block, express=express) if qos is not None else None
        )
        self.publisher: Publisher | None = (
            None if qos is not None else transport.publisher(key, express=express)
        )
        #: writes KEEP_ALL refused after max_blocking_time (history full of unacknowledged data)
        self.write_failures = 0
        #: messages written while no reader was matched (only counted with ``count_unmatched``)
        self.unmatched = 0

    def send(self, payload: bytes, stamp_ns: int, *, count_unmatched: bool = False) -> bool:
        """Publish one message; False (and counted) if a KEEP_ALL history stayed full.

        ``count_unmatched``: count a message written while no reader is matched (it reaches no
        one: a VOLATILE writer delivers only within a match); for low-rate keys whose receiver
        reconciles against the sender, such as commands. A reader away (its session lost, its
        match to resume) is not "no one": the message reaches it or is reported lost to it when
        it is back."""
        if self.writer is None:
            if count_unmatched and not self.matched:
                self.unmatched += 1
            assert self.publisher is not None
            self.publisher.put(payload)
            return True
        try:
            writer = self.writer
            writer.note_audience = count_unmatched
            writer.write(payload, stamp_ns=stamp_ns)
            if count_unmatched and not writer.last_write_had_audience:
                self.unmatched += 1
            return True
        except HistoryFullError as exc:
            self.write_failures += 1
            if self.write_failures in (1, 10, 100) or self.write_failures % 1000 == 0:
                log.error("%s: message not sent (#%d): %s", self.key, self.write_failures, exc)
            return False

    def unchanged(self) -> None:
        """The local cache held a repeat back: tell the channel the topic is alive and current."""
        if self.writer is not None:
            self.writer.assert_unchanged()

    def acknowledged_through(self) -> int | None:
        """The channel seq every reliable reader acknowledged so far (None without the channel)."""
        return self.writer.acknowledged_through() if self.writer is not None else None

    def latest_undeliverable(self) -> bool:
        """The channel can no longer deliver the last message sent (False without it)."""
        return self.writer is not None and self.writer.latest_undeliverable()

    def retune(
        self, *, depth: int, deadline_s: float, heartbeat_period_s: float | None = None
    ) -> None:
        """Apply a QoS assignment's depth, deadline and heartbeat period (None: unchanged) in
        place (no-op without the channel)."""
        if self.writer is not None:
            self.writer.retune(
                depth=depth, deadline_s=deadline_s, heartbeat_period_s=heartbeat_period_s
            )

    @property
    def qos(self) -> QosProfile | None:
        """The QoS in force (the writer's), None in plain mode."""
        return self.writer.qos if self.writer is not None else None

    def stats(self) -> WriterStats | None:
        return self.writer.stats() if self.writer is not None else None

    def totals(self) -> dict[str, int]:
        """Channel counters of this key (zeros without the channel)."""
        return writer_totals(self.stats(), self.write_failures)

    @property
    def matched(self) -> bool:
        """A reader is listening: a matched reliable reader, or for a plain publisher any Zenoh
        subscriber whose declaration has reached this side's router (so the first messages are
        not put before the route through a router mesh exists)."""
        if self.writer is not None:
            return self.writer.matched_count > 0
        assert self.publisher is not None
        return self.publisher.matching

    @property
    def awaited(self) -> bool:
        """A reader whose session was lost may resume its match (never without the channel)."""
        return self.writer is not None and self.writer.awaited_count > 0

    def wait_for_acknowledgments(self, timeout_s: float) -> bool:
        """True once every matched reader acknowledged everything (at once without the channel)."""
        return self.writer is None or self.writer.wait_for_acknowledgments(timeout_s)

    def close(self, wait_s: float = 0.5) -> bool:
        """Wait (bounded) until every matched reader acknowledged everything, then close; True if
        it did (always True without the channel)."""
        if self.writer is None:
            assert self.publisher is not None
            self.publisher.undeclare()
            return True
        acknowledged = self.wait_for_acknowledgments(wait_s)
        self.writer.close()
        return acknowledged


class FrameOutlet:
    """The ``Outlet`` of a large sensor (camera, point cloud) through the reliable channel: a
    ``FrameWriter`` whose QoS counts frames (``frames_qos``), so a frame travels as fragments of
    one radio frame and only missing fragments are resent.

    It answers the sensor path's questions as an ``Outlet`` does, with three differences, each
    because a frame is many channel samples: the channel counters (``totals``) count fragments;
    there is no per-sample acknowledgement for the local cache's staleness bookkeeping
    (``acknowledged_through`` is None); and a QoS assignment's depth, which counts samples of
    small topics, leaves the frame history alone (the assigned rate still applies).
    """

    def __init__(
        self,
        transport: Transport,
        key: str,
        qos: QosProfile,
        max_frame_bytes: int,
        fragment_bytes: int = DEFAULT_FRAGMENT_BYTES,
    ):
        self.key = key
        self.frames = FrameWriter(
            transport,
            key,
            qos,
            max_frame_bytes=max_frame_bytes,
            fragment_bytes=fragment_bytes,
            block=True,
        )
        self._qos = qos
        #: frames refused: a KEEP_ALL frame history stayed full, or a frame over max_frame_bytes
        self.write_failures = 0

    def send(self, payload: bytes, stamp_ns: int, *, count_unmatched: bool = False) -> bool:
        try:
            self.frames.write(payload, stamp_ns=stamp_ns)
            return True
        except (HistoryFullError, FragmentError) as exc:
            self.write_failures += 1
            if self.write_failures in (1, 10, 100) or self.write_failures % 1000 == 0:
                log.error("%s: frame not sent (#%d): %s", self.key, self.write_failures, exc)
            return False

    def unchanged(self) -> None:
        """A repeated frame is held back by the local cache; nothing is said on the channel."""

    def acknowledged_through(self) -> int | None:
        return None

    def latest_undeliverable(self) -> bool:
        return False

    def retune(
        self, *, depth: int, deadline_s: float, heartbeat_period_s: float | None = None
    ) -> None:
        """A QoS assignment's depth counts samples of small topics: the frame history stays,
        and so does the fragment channel's own heartbeat ([frames_qos])."""

    @property
    def qos(self) -> QosProfile:
        return self._qos

    def stats(self) -> WriterStats:
        return self.frames.stats().channel

    def totals(self) -> dict[str, int]:
        """The fragment channel's counters (in fragments) and the frames refused."""
        return writer_totals(self.stats(), self.write_failures)

    @property
    def matched(self) -> bool:
        return self.frames.matched_count > 0

    def wait_for_acknowledgments(self, timeout_s: float) -> bool:
        return self.frames.wait_for_acknowledgments(timeout_s)

    def close(self, wait_s: float = 0.5) -> bool:
        acknowledged = self.wait_for_acknowledgments(wait_s)
        self.frames.close()
        return acknowledged


class Inlet:
    """Where one key expression's messages arrive: a reliable-channel ``Reader`` or a plain
    subscription. ``on_message(key, payload)`` runs on Zenoh's callback thread (through the
    Reader's inline delivery: one call at a time, in order per writer; samples a NACK recovered
    on the Reader's control thread, in turn): it must only queue.

    Inline because an Inlet's messages are few (commands, reports, configurations): a delivery
    thread of its own would sit in a blocking Zenoh receive, which wakes 10 times a second to
    look for signals and takes the process's GIL each time; a robot keeps three Inlets, and
    their delivery threads were a fifth of an idle fleet worker's wake-ups (issue 17).

    ``on_incompatible(key, policy)`` is called once per key whose publisher disagrees on the mode
    (a plain put to a channel Inlet, or a channel-headed sample to a plain one), and once per
    incompatible channel writer (key ""), from the Inlet's thread; such samples are refused and
    counted in ``refused`` per key.
    """

    def __init__(
        self,
        transport: Transport,
        key_expr: str,
        qos: QosProfile | None,
        on_message: Callable[[str, bytes], None],
        *,
        on_incompatible: Callable[[str, QosPolicyKind], None] | None = None,
        on_lost: Callable[[MessageLostStatus], None] | None = None,
    ) -> None:
        self.key_expr = key_expr
        self._on_incompatible = on_incompatible
        self._lock = threading.Lock()
        self._refused: dict[str, int] = {}
        self.reader: Reader | None = None
        self._handle: Handle | None = None
        if qos is not None:
            self.reader = Reader(
                transport,
                key_expr,
                qos,
                lambda payload, info: on_message(info.key, payload),
                events=ReaderEventCallbacks(
                    incompatible_qos=self._on_channel_incompatible, message_lost=on_lost
                ),
                inline_delivery=True,
            )
        else:

            def on_plain(key: str, payload: bytes, attachment: bytes | None) -> None:
                if attachment is None:
                    on_message(key, payload)
                else:
                    self._refuse(key)

            self._handle = transport.subscribe(key_expr, on_plain)

    def _on_channel_incompatible(self, status: IncompatibleQosStatus) -> None:
        key = status.peer[len(PLAIN_PEER) :] if status.peer.startswith(PLAIN_PEER) else ""
        if self._on_incompatible is not None:
            self._on_incompatible(key, status.last_policy_kind)

    def _refuse(self, key: str) -> None:
        with self._lock:
            seen = self._refused.get(key, 0)
            if not seen and len(self._refused) >= 1024:
                key, seen = "(other keys)", self._refused.get("(other keys)", 0)
            self._refused[key] = seen + 1
        if not seen and self._on_incompatible is not None:
            self._on_incompatible(key, QosPolicyKind.RELIABILITY)

    @property
    def refused(self) -> dict[str, int]:
        """Samples refused per key because their publisher disagrees on the mode."""
        if self.reader is not None:
            return self.reader.plain_samples()
        with self._lock:
            return dict(self._refused)

    @property
    def qos(self) -> QosProfile | None:
        """The QoS in force (the reader's, which follows assignments), None in plain mode."""
        return self.reader.qos if self.reader is not None else None

    def stats(self) -> ReaderStats | None:
        return self.reader.stats() if self.reader is not None else None

    def close(self) -> None:
        if self.reader is not None:
            self.reader.close()
        elif self._handle is not None:
            self._handle.undeclare()


class Draining(Protocol):
    """What ``drain`` needs of an outlet."""

    def wait_for_acknowledgments(self, timeout_s: float) -> bool: ...
    def acknowledged_through(self) -> int | None: ...


def drain(
    outlets: Sequence[Draining],
    *,
    stall_s: float,
    limit_s: float,
    poll_s: float = 0.05,
    clock: Callable[[], float] = time.monotonic,
) -> bool:
    """Wait until every outlet's readers acknowledged everything it wrote; True if they did.

    Gives up after ``stall_s`` without any acknowledgement advancing, or after ``limit_s`` in
    all. Why paced, not a fixed timeout: a robot that stops while the CEDDP is behind (an
    overload with QoS control off) had samples in flight for longer than its 2 s wait, and its
    final report queued behind them on the same link: 20 of 50 robots' final reports never
    arrived (issue 17, benchmarks/RESULTS.md). A CEDDP that is draining keeps acknowledging, so
    the robot waits for it; a dead one does not, so the robot stops after ``stall_s`` as before."""
    started = last_progress = clock()
    pending = list(outlets)
    seen: dict[int, int | None] = {id(o): o.acknowledged_through() for o in pending}
    while pending:
        now = clock()
        if now - last_progress >= stall_s or now - started >= limit_s:
            return False
        still: list[Draining] = []
        for outlet in pending:
            if outlet.wait_for_acknowledgments(poll_s / max(len(pending), 1)):
                last_progress = clock()
                continue
            through = outlet.acknowledged_through()
            before = seen[id(outlet)]
            if through is not None and (before is None or through > before):
                seen[id(outlet)] = through
                last_progress = clock()
            still.append(outlet)
        pending = still
    return True
