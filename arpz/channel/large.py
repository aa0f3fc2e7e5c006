"""``FrameWriter`` / ``FrameReader``: large samples (camera frames, point clouds) over the channel.

Each frame is cut into fragments of one radio frame (``arpz.core.protocol.fragments``) and every
fragment is one sample of a reliable ``Writer`` with batching off, so Zenoh never fragments
anything and never packs a 48 KiB batch; the channel's ACKNACK ranges NACK exactly the missing
fragments and the writer resends only those (selective repeat, as RTPS's NACK_FRAG). The reader
reassembles per writer, bounded in memory, and the newest frame wins: an older frame still
incomplete when a newer one starts is dropped and counted (KEEP_LAST 1 for video). See "Large
samples" in docs/reliability.md.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable
from typing import Final

import msgspec

from arpz.channel.reader import Reader
from arpz.channel.writer import Writer
from arpz.core.protocol.events import (
    DataInfo,
    MatchedStatus,
    ReaderEventCallbacks,
    WriterEventCallbacks,
)
from arpz.core.protocol.fragments import (
    DEFAULT_FRAGMENT_BYTES,
    HEADER_BYTES,
    FragmentError,
    Reassembler,
    ReassemblyStats,
    fragment_count,
    split,
)
from arpz.core.protocol.qos import HistoryPolicy, QosError, QosProfile
from arpz.core.protocol.reader_machine import ReaderStats
from arpz.core.protocol.timers import Clock
from arpz.core.protocol.writer_machine import WriterStats
from arpz.core.transport import Transport

#: a 640x480 RGB frame (921 600 bytes) or a 1 MB point cloud; a larger frame is refused
DEFAULT_MAX_FRAME_BYTES: Final = 2**20
#: the most a frame history (frames x largest frame) may hold: KEEP_ALL with the channel's default
#: ``max_samples`` (5000) would otherwise reserve the right to keep gigabytes
MAX_HISTORY_BYTES: Final = 512 * 2**20

#: video: RELIABLE, KEEP_LAST 1 frame (its fragments are resent until a newer frame replaces it)
QOS_VIDEO: Final = QosProfile(depth=1)
#: every frame, in order: KEEP_ALL with room for 8 frames in the writer's history
QOS_FRAMES_ALL: Final = QosProfile(history=HistoryPolicy.KEEP_ALL, max_samples=8)


def fragment_qos(qos: QosProfile, max_frame_bytes: int, fragment_bytes: int) -> QosProfile:
    """The channel QoS of the fragments for a QoS counted in frames: depth and ``max_samples``
    times the fragments of the largest frame, batching off (one fragment per Zenoh message)."""
    per_frame = fragment_count(max_frame_bytes, fragment_bytes)
    if qos.capacity * max_frame_bytes > MAX_HISTORY_BYTES:
        bound = "depth" if qos.history is HistoryPolicy.KEEP_LAST else "max_samples"
        raise QosError(
            f"a history of {qos.capacity} frames of up to {max_frame_bytes} bytes exceeds "
            f"{MAX_HISTORY_BYTES} bytes: lower {bound} "
            "(frames, not fragments) or max_frame_bytes"
        )
    return msgspec.structs.replace(
        qos,
        depth=qos.depth * per_frame,
        max_samples=qos.max_samples * per_frame,
        batch_max_samples=1,
    )


class FrameInfo(msgspec.Struct, frozen=True, gc=False):
    """Where a delivered frame came from; ``stamp_ns`` is the writer's (wall clock, ns), the same
    on all its fragments, so ``time.time_ns() - stamp_ns`` is the frame's latency."""

    key: str
    writer: str
    frame_id: int
    stamp_ns: int
    fragments: int


class FrameWriterStats(msgspec.Struct, frozen=True):
    frames_sent: int
    #: frames whose fragments were not all written (``write`` raised, e.g. KEEP_ALL full)
    frames_aborted: int
    bytes_sent: int
    fragments_sent: int
    #: the fragment channel's own counters (sent, retransmitted, nacks, lost, ...)
    channel: WriterStats


class FrameReaderStats(msgspec.Struct, frozen=True):
    #: frames delivered, dropped (incomplete, over a bound, too large) and missing
    frames: ReassemblyStats
    #: the fragment channel's own counters (delivered, lost, retransmitted, nacks, ...)
    channel: ReaderStats


class FrameWriter:
    """Publishes frames of up to ``max_frame_bytes`` on ``key``; ``qos`` counts frames (``depth``,
    ``max_samples``), each sent as fragments of ``fragment_bytes``. The reader must use the same
    ``max_frame_bytes`` and ``fragment_bytes`` so that its window matches the writer's history."""

    def __init__(
        self,
        transport: Transport,
        key: str,
        qos: QosProfile,
        *,
        max_frame_bytes: int = DEFAULT_MAX_FRAME_BYTES,
        fragment_bytes: int = DEFAULT_FRAGMENT_BYTES,
        events: WriterEventCallbacks | None = None,
        block: bool = True,
        clock: Clock | None = None,
    ) -> None:
        if fragment_bytes < 1 or max_frame_bytes < 1:
            raise FragmentError("fragment_bytes and max_frame_bytes must be >= 1")
        self.key = key
        self.max_frame_bytes, self.fragment_bytes = max_frame_bytes, fragment_bytes
        self.writer = Writer(
            transport,
            key,
            fragment_qos(qos, max_frame_bytes, fragment_bytes),
            events=events,
            block=block,
            clock=clock,
            # a frame fragment (header included) is never cut again by the channel
            fragment_bytes=fragment_bytes + HEADER_BYTES,
            # frames yield to the robot's other traffic on a busy link (issue 39)
            bulk=True,
        )
        #: held for a whole frame, so that its fragments get consecutive seqs
        self._write_lock = threading.Lock()
        #: the counters only, so that ``stats()`` never waits for a frame to go out
        self._lock = threading.Lock()
        self._next_id = 1
        self._sent = self._aborted = self._bytes = self._fragments = 0

    def write(self, payload: bytes, *, stamp_ns: int | None = None) -> int:
        """Send one frame; returns its frame id (1, 2, ...). Raises ``FragmentError`` for a frame
        over ``max_frame_bytes``; with KEEP_ALL, ``HistoryFullError`` if the readers fall more
        than ``max_samples`` frames behind (the frame is then counted ``frames_aborted``)."""
        if len(payload) > self.max_frame_bytes:
            raise FragmentError(
                f"a frame of {len(payload)} bytes exceeds max_frame_bytes {self.max_frame_bytes}"
            )
        stamp = time.time_ns() if stamp_ns is None else stamp_ns
        with self._write_lock:
            frame_id, self._next_id = self._next_id, self._next_id + 1
            written = 0
            try:
                for fragment in split(frame_id, payload, self.fragment_bytes):
                    self.writer.write(fragment, stamp_ns=stamp)
                    written += 1
            except BaseException:
                with self._lock:
                    self._aborted += 1
                    self._fragments += written
                raise
            with self._lock:
                self._sent += 1
                self._bytes += len(payload)
                self._fragments += written
        return frame_id

    @property
    def matched_count(self) -> int:
        return self.writer.matched_count

    def wait_for_acknowledgments(self, timeout_s: float) -> bool:
        return self.writer.wait_for_acknowledgments(timeout_s)

    def stats(self) -> FrameWriterStats:
        with self._lock:
            sent, aborted, sent_bytes, fragments = (
                self._sent,
                self._aborted,
                self._bytes,
                self._fragments,
            )
        return FrameWriterStats(sent, aborted, sent_bytes, fragments, self.writer.stats())

    def close(self) -> None:
        self.writer.close()

    def __enter__(self) -> FrameWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class FrameReader:
    """Receives frames from every ``FrameWriter`` whose key matches ``key_expr``;
    ``on_frame(payload, info)`` runs on the reader's own threads, one call at a time, frames in
    order per writer. At most ``max_frames_in_assembly`` frames and ``max_assembly_bytes`` bytes
    are being reassembled at once (over all writers); what exceeds them is dropped and counted."""

    def __init__(
        self,
        transport: Transport,
        key_expr: str,
        qos: QosProfile,
        on_frame: Callable[[bytes, FrameInfo], None],
        *,
        max_frame_bytes: int = DEFAULT_MAX_FRAME_BYTES,
        fragment_bytes: int = DEFAULT_FRAGMENT_BYTES,
        max_frames_in_assembly: int = 8,
        max_assembly_bytes: int = 64 * 2**20,
        events: ReaderEventCallbacks | None = None,
        clock: Clock | None = None,
    ) -> None:
        self.key_expr = key_expr
        self._on_frame = on_frame
        self._lock = threading.Lock()
        self._reassembler = Reassembler(
            max_frames=max_frames_in_assembly,
            max_bytes=max_assembly_bytes,
            max_frame_bytes=max_frame_bytes,
            in_order=True,  # the channel delivers each writer's fragments in seq order
        )
        events = events or ReaderEventCallbacks()
        self._user_matched = events.matched
        self.reader = Reader(
            transport,
            key_expr,
            fragment_qos(qos, max_frame_bytes, fragment_bytes),
            self._on_fragment,
            events=dataclasses.replace(events, matched=self._on_matched),
            clock=clock,
        )

    def _on_matched(self, status: MatchedStatus) -> None:
        """A writer that left can never complete the frame it was sending: drop it (counted
        incomplete) rather than hold its buffer until the bounds evict it. The channel delivers
        the writer's last fragments before this event."""
        if status.current_count_change < 0:
            with self._lock:
                for source in self._reassembler.sources:
                    if source.endswith(f"#{status.peer}"):
                        self._reassembler.drop_source(source)
        if self._user_matched is not None:
            self._user_matched(status)

    def _on_fragment(self, payload: bytes, info: DataInfo) -> None:
        with self._lock:
            done = self._reassembler.add(f"{info.key}#{info.writer}", payload, info.stamp_ns)
        if done is not None:
            frame_info = FrameInfo(
                info.key, info.writer, done.frame_id, done.stamp_ns, done.fragments
            )
            self._on_frame(done.payload, frame_info)

    @property
    def matched_count(self) -> int:
        return self.reader.matched_count

    def stats(self) -> FrameReaderStats:
        with self._lock:
            frames = self._reassembler.stats()
        return FrameReaderStats(frames, self.reader.stats())

    def close(self) -> None:
        self.reader.close()

    def __enter__(self) -> FrameReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
