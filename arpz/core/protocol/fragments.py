"""Large samples as fragments of one radio frame each: the split and a bounded reassembly, pure.

Why: Zenoh fragments a message larger than its batch (up to 64 KiB, one UDP datagram) and loses the
whole message when one fragment is lost; at 10 % loss per WiFi frame a 921 600-byte camera frame
practically never arrives, and resending all of it does not help. arpz cuts a large sample into
fragments small enough that Zenoh never cuts them again (``DEFAULT_FRAGMENT_BYTES`` plus the headers
fit one 1500-byte frame), sends each fragment as one sample of the reliable channel with its own
seq, and the channel's ACKNACK ranges then ask for exactly the missing fragments (what RTPS does
with NACK_FRAG), selective repeat included. This module knows nothing of the channel: it turns a
payload into fragments and fragments back into payloads, with every bound explicit and every drop
counted.

A fragment is a 25-byte header (``"!BQIIII"``: version = 1, frame id (u64, 1, 2, ... per writer),
index (u32), count (u32), total length (u32), chunk size (u32)) followed by the bytes
``[index * chunk, min((index + 1) * chunk, total))`` of the frame. ``count`` must equal
``max(1, ceil(total / chunk))``; a fragment that disagrees with its header or with the other
fragments of its frame is refused and counted in ``bad_fragments``.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterator
from typing import Final

import msgspec

from arpz.core.errors import ArpzError

VERSION: Final = 1
HEADER: Final = struct.Struct("!BQIIII")
HEADER_BYTES: Final = HEADER.size
#: payload bytes per fragment. 1280 + this header (25) + the channel's DATA or RESEND attachment
#: (26 or 30) + Zenoh's framing and key (about 60 measured for a resend on its own key) stays
#: under 1472 bytes, the largest UDP payload of one 1500-byte frame; docs/reliability.md
DEFAULT_FRAGMENT_BYTES: Final = 1280
#: the largest fragment that still fits one Zenoh batch (64 KiB) with its headers (a larger one
#: would be cut by Zenoh again, and lost whole when one of its pieces is)
MAX_FRAGMENT_BYTES: Final = 60 * 1024
#: payload bytes per fragment on a stream link (TCP, TLS, QUIC...): the transport resends its own
#: segments, so a fragment need not fit a radio frame, only a Zenoh batch; 48 times fewer channel
#: samples per frame is what lifts arpz's flat-out goodput on TCP from 0.23-0.25x to 0.95-1.16x
#: raw Zenoh's, against 0.75-0.91x with 32 KiB (benchmarks/large_messages.py, RESULTS.md)
STREAM_FRAGMENT_BYTES: Final = MAX_FRAGMENT_BYTES
#: the largest frame the header can describe
MAX_FRAME_BYTES: Final = 2**32 - 1
#: dropped frame ids remembered per source (so that their late fragments count as stale)
_MAX_EVICTED: Final = 1024


class FragmentError(ArpzError, ValueError):
    """A frame that cannot be split as asked (too large, bad fragment size); says which bound."""


def fragment_count(total: int, fragment_bytes: int) -> int:
    """Fragments a frame of ``total`` bytes takes (an empty frame is one empty fragment)."""
    return max(1, math.ceil(total / fragment_bytes))


def split(frame_id: int, payload: bytes, fragment_bytes: int) -> Iterator[bytes]:
    """The fragments of one frame, in index order (a generator: the caller sends each as it comes,
    so a frame's fragments are never all copied at once)."""
    if not 1 <= fragment_bytes <= MAX_FRAME_BYTES:
        raise FragmentError(f"fragment_bytes must be 1 .. {MAX_FRAME_BYTES}, got {fragment_bytes}")
    total = len(payload)
    if total > MAX_FRAME_BYTES:
        raise FragmentError(f"a frame of {total} bytes exceeds {MAX_FRAME_BYTES}")
    if not 1 <= frame_id < 2**64:
        raise FragmentError(f"frame id must be 1 .. 2^64 - 1, got {frame_id}")
    count = fragment_count(total, fragment_bytes)
    view = memoryview(payload)
    for index in range(count):
        start = index * fragment_bytes
        head = HEADER.pack(VERSION, frame_id, index, count, total, fragment_bytes)
        yield head + view[start : start + fragment_bytes]


class Fragment(msgspec.Struct, frozen=True, gc=False):
    frame_id: int
    index: int
    count: int
    total: int
    chunk: int
    data: memoryview


def parse(fragment: bytes) -> Fragment | None:
    """The fragment, or None when its header is malformed or disagrees with its length."""
    if len(fragment) < HEADER_BYTES:
        return None
    version, frame_id, index, count, total, chunk = HEADER.unpack_from(fragment)
    if version != VERSION or frame_id == 0 or chunk == 0:
        return None
    if count != fragment_count(total, chunk) or index >= count:
        return None
    data = memoryview(fragment)[HEADER_BYTES:]
    if len(data) != min(chunk, total - index * chunk):
        return None
    return Fragment(frame_id, index, count, total, chunk, data)


class Completed(msgspec.Struct, frozen=True, gc=False):
    """A reassembled frame. ``stamp_ns`` is the one its first fragment brought (the writer stamps
    every fragment of a frame alike)."""

    source: str
    frame_id: int
    payload: bytes
    fragments: int
    stamp_ns: int


class ReassemblyStats(msgspec.Struct, frozen=True):
    """Every frame a source sent after the first one seen ends in exactly one of
    ``frames_delivered``, ``frames_dropped_incomplete``, ``frames_dropped_over_limit``,
    ``frames_too_large``, ``frames_missing`` or (for now) ``in_assembly``; frames after the last
    one delivered that never arrived at all cannot be known here (the channel counts their
    fragments lost)."""

    frames_delivered: int
    bytes_delivered: int
    #: older frames still incomplete when a newer one of the same source completed (or, in order,
    #: when a newer one began): the newest frame wins, as KEEP_LAST 1 for video asks
    frames_dropped_incomplete: int
    #: evicted (the oldest first) to keep ``max_frames`` and ``max_bytes``
    frames_dropped_over_limit: int
    #: announced a total beyond ``max_frame_bytes``: refused at its first fragment
    frames_too_large: int
    #: frame ids passed by a delivered frame of which not one fragment arrived
    frames_missing: int
    fragments_received: int
    fragments_duplicate: int
    #: for a frame already delivered, dropped or passed (a late resend, a duplicate)
    fragments_stale: int
    #: malformed, or disagreeing with the other fragments of their frame
    bad_fragments: int
    #: frames being assembled now, and the bytes reserved for them
    in_assembly: int
    assembly_bytes: int


class _Partial:
    __slots__ = ("buffer", "chunk", "count", "have", "missing", "source", "stamp_ns", "total")

    def __init__(self, source: str, first: Fragment, stamp_ns: int) -> None:
        self.source = source
        self.total, self.count, self.chunk = first.total, first.count, first.chunk
        self.buffer = bytearray(first.total)
        self.have = bytearray(first.count)
        self.missing = first.count
        self.stamp_ns = stamp_ns


class _Source:
    __slots__ = ("done_through", "evicted")

    def __init__(self, done_through: int) -> None:
        #: every frame id up to this one is settled (delivered, dropped or missing)
        self.done_through = done_through
        #: ids above ``done_through`` already dropped (over a limit, too large): their later
        #: fragments are stale, and they are not counted missing when passed
        self.evicted: set[int] = set()


class Reassembler:
    """Fragments in (any order, duplicates, losses), whole frames out, memory bounded.

    ``max_frames`` frames and ``max_bytes`` bytes (their announced totals) may be in assembly at
    once, over all sources; beyond that the oldest frame in assembly is dropped and counted.
    A frame announcing more than ``max_frame_bytes`` is refused at its first fragment. At most
    ``max_sources`` sources are remembered (the least recently started one is forgotten).

    A completed frame is delivered unless a newer frame of its source was delivered already; on
    delivery the older incomplete frames of that source are dropped (counted). ``in_order=True``
    is for fragments that arrive in the order they were sent, missing ones aside (the reliable
    channel delivers in seq order): an incomplete frame can then never complete once a fragment of
    a newer frame arrived, so it is dropped at once, which keeps at most one frame per source in
    assembly.
    """

    def __init__(
        self,
        *,
        max_frames: int = 4,
        max_bytes: int = 64 * 2**20,
        max_frame_bytes: int = 16 * 2**20,
        max_sources: int = 1024,
        in_order: bool = False,
    ) -> None:
        for name, value in (
            ("max_frames", max_frames),
            ("max_bytes", max_bytes),
            ("max_frame_bytes", max_frame_bytes),
            ("max_sources", max_sources),
        ):
            if value < 1:
                raise FragmentError(f"{name} must be >= 1, got {value}")
        self.max_frames, self.max_bytes = max_frames, max_bytes
        self.max_frame_bytes, self.max_sources = max_frame_bytes, max_sources
        self.in_order = in_order
        #: (source, frame id) -> partial, oldest first (dicts keep insertion order)
        self._partials: dict[tuple[str, int], _Partial] = {}
        self._sources: dict[str, _Source] = {}
        self._assembly_bytes = 0
        self._delivered = self._bytes_delivered = self._incomplete = self._over_limit = 0
        self._too_large = self._missing = self._received = self._duplicate = 0
        self._stale = self._bad = 0

    def add(self, source: str, data: bytes, stamp_ns: int = 0) -> Completed | None:
        """Take one fragment of ``source``; returns the frame it completes, if any."""
        self._received += 1
        frag = parse(data)
        if frag is None:
            self._bad += 1
            return None
        state = self._sources.get(source)
        if state is None:
            # frames before the first one seen are before this reader: not counted missing
            state = self._remember(source, _Source(frag.frame_id - 1))
        fid = frag.frame_id
        if fid <= state.done_through or fid in state.evicted:
            self._stale += 1
            return None
        partial = self._partials.get((source, fid))
        if partial is None:
            if self.in_order:
                self._drop_older(source, state, fid)
            if frag.total > min(self.max_frame_bytes, self.max_bytes):
                self._too_large += 1
                self._evict(state, fid)
                return None
            self._make_room(frag.total)
            partial = _Partial(source, frag, stamp_ns)
            self._partials[(source, fid)] = partial
            self._assembly_bytes += frag.total
        elif (frag.total, frag.count, frag.chunk) != (partial.total, partial.count, partial.chunk):
            self._bad += 1
            return None
        if partial.have[frag.index]:
            self._duplicate += 1
            return None
        partial.have[frag.index] = 1
        partial.missing -= 1
        start = frag.index * frag.chunk
        partial.buffer[start : start + len(frag.data)] = frag.data
        if partial.missing:
            return None
        del self._partials[(source, fid)]
        self._assembly_bytes -= partial.total
        self._drop_older(source, state, fid)
        state.done_through = fid
        self._delivered += 1
        self._bytes_delivered += partial.total
        return Completed(source, fid, bytes(partial.buffer), partial.count, partial.stamp_ns)

    def drop_source(self, source: str) -> None:
        """The source is gone (its writer closed or died): its frames in assembly can never
        complete; drop them, counted as incomplete."""
        for key in [k for k in self._partials if k[0] == source]:
            self._discard(key)
            self._incomplete += 1
        self._sources.pop(source, None)

    @property
    def sources(self) -> list[str]:
        """The sources remembered now (at most ``max_sources``)."""
        return list(self._sources)

    def stats(self) -> ReassemblyStats:
        return ReassemblyStats(
            frames_delivered=self._delivered,
            bytes_delivered=self._bytes_delivered,
            frames_dropped_incomplete=self._incomplete,
            frames_dropped_over_limit=self._over_limit,
            frames_too_large=self._too_large,
            frames_missing=self._missing,
            fragments_received=self._received,
            fragments_duplicate=self._duplicate,
            fragments_stale=self._stale,
            bad_fragments=self._bad,
            in_assembly=len(self._partials),
            assembly_bytes=self._assembly_bytes,
        )

    def _remember(self, source: str, state: _Source) -> _Source:
        if len(self._sources) >= self.max_sources:
            oldest = next(iter(self._sources))
            self.drop_source(oldest)
        self._sources[source] = state
        return state

    def _drop_older(self, source: str, state: _Source, fid: int) -> None:
        """Settle every frame id of ``source`` below ``fid``: incomplete ones are dropped,
        evicted ones were counted already, the rest never showed a fragment (missing)."""
        passed = fid - 1 - state.done_through
        if passed <= 0:
            return
        for key in [k for k in self._partials if k[0] == source and k[1] < fid]:
            self._discard(key)
            self._incomplete += 1
            passed -= 1
        evicted = {e for e in state.evicted if e < fid}
        state.evicted -= evicted
        self._missing += passed - len(evicted)
        state.done_through = fid - 1

    def _make_room(self, total: int) -> None:
        while self._partials and (
            len(self._partials) >= self.max_frames or self._assembly_bytes + total > self.max_bytes
        ):
            key = next(iter(self._partials))
            self._discard(key)
            self._over_limit += 1
            state = self._sources.get(key[0])
            if state is not None:
                self._evict(state, key[1])

    def _evict(self, state: _Source, fid: int) -> None:
        state.evicted.add(fid)
        if len(state.evicted) > _MAX_EVICTED:  # only without in_order can they pile up
            state.evicted.discard(min(state.evicted))

    def _discard(self, key: tuple[str, int]) -> None:
        partial = self._partials.pop(key)
        self._assembly_bytes -= partial.total


class SampleParts:
    """The fragments of one channel sample (``arpz.core.protocol.wire.DATA_FRAG``) received so far:
    the sample's bytes in place, which fragments arrived, and what the reader knows of the rest.
    The reader machine keeps one per sample seq still incomplete, within its byte bound."""

    __slots__ = (
        "asked_high",
        "asked_s",
        "buffer",
        "chunk",
        "closed_s",
        "count",
        "flags",
        "gap_s",
        "have",
        "high",
        "missing",
        "stamp_ns",
        "total",
    )

    def __init__(self, total: int, chunk: int, stamp_ns: int) -> None:
        self.total, self.chunk, self.stamp_ns = total, chunk, stamp_ns
        self.count = fragment_count(total, chunk)
        self.buffer = bytearray(total)
        self.have = bytearray(self.count)
        self.missing = self.count
        #: the highest index received (-1: none yet)
        self.high = -1
        #: flags to apply when the sample completes (ACK_REQUEST)
        self.flags = 0
        #: when a fragment below ``high`` was first seen missing (inf: none), and when the
        #: writer was known to have sent them all (its last fragment, a later sample, a
        #: heartbeat past it): the reader asks for what is missing once that is old enough
        self.gap_s = math.inf
        self.closed_s = math.inf
        #: the last request for fragments of this sample: when, and the highest index asked
        self.asked_s = -math.inf
        self.asked_high = -1

    def add(self, index: int, data: bytes) -> bool | None:
        """Store fragment ``index``: True if new, False if a duplicate, None if its length
        disagrees with the sample's (refused)."""
        start = index * self.chunk
        if index >= self.count or len(data) != min(self.chunk, self.total - start):
            return None
        if self.have[index]:
            return False
        self.have[index] = 1
        self.missing -= 1
        self.buffer[start : start + len(data)] = data
        if index > self.high:
            self.high = index
        return True

    def missing_runs(self, first: int, last: int) -> list[tuple[int, int]]:
        """Inclusive runs of the indices ``first .. last`` not received yet."""
        runs: list[tuple[int, int]] = []
        have = self.have
        at = first
        while at <= last:
            lo = have.find(0, at, last + 1)
            if lo < 0:
                break
            hi = have.find(1, lo, last + 1)
            hi = last if hi < 0 else hi - 1
            runs.append((lo, hi))
            at = hi + 1
        return runs
