"""Byte layouts and keys of the reliable protocol (docs/reliability.md describes them).

Fixed-size big-endian ``struct`` layouts rather than msgpack: every field has a fixed offset, the
DATA header costs 26 bytes and one ``unpack_from``, and a malformed message is recognised by its
length before any field is trusted. Decoders return None for anything malformed so that callers
count and ignore it.
"""

from __future__ import annotations

import functools
import itertools
import struct
from collections.abc import Sequence
from typing import Final, NamedTuple

VERSION: Final = 1

# DATA header, carried in the Zenoh attachment of a sample on the topic key (or on the directed
# resend key): version, flags, writer guid, seq, source stamp.
DATA: Final = struct.Struct("!BB8sQq")
# A resend's header (on the directed resend key only): DATA, then the count of the ACKNACK it
# answers, so that the reader times its NACK round trip exactly, whatever other NACKs and resends
# are in flight (timing from the latest NACK sent underestimated a 100 ms round trip as 2.5 ms).
RESEND: Final = struct.Struct("!BB8sQqI")
F_RETRANSMIT: Final = 0x01
F_ACK_REQUEST: Final = 0x02
F_BATCH: Final = 0x04
#: a fragment of a sample larger than the writer's fragment size (DATA_FRAG; never batched)
F_FRAGMENT: Final = 0x08

# DATA_FRAG (as RTPS's): the DATA header, then the fragment's index, the sample's total length
# and the fragment size (u32 each); the payload is bytes ``[index * chunk, (index + 1) * chunk)``
# of the sample. The sample keeps ONE seq: it is delivered whole or counted lost once, and only
# the fragments a reader misses are resent (ACKNACK_FRAG). 38 bytes, and its resend's 42 (with
# the ACKNACK count it answers): never the length of a DATA (26), a resend (30) or a batch's
# attachment (20 + 12 n).
DATA_FRAG: Final = struct.Struct("!BB8sQqIII")
RESEND_FRAG: Final = struct.Struct("!BB8sQqIIII")

# DATA batch header, in the attachment of a message carrying consecutive samples (first .. first
# + n - 1) whose payloads are concatenated: version, flags (F_BATCH set), writer, first seq, n;
# then the n source stamps (i64 each), then the n payload lengths (u32 each). Never 26 or 30
# bytes long, so never taken for DATA or a resend. Stamps and lengths are two arrays, not n
# pairs, so that one ``struct`` call packs or unpacks them all.
BATCH: Final = struct.Struct("!BB8sQH")
#: bytes per sample after the batch header: a stamp and a length
BATCH_ENTRY_SIZE: Final = 12
#: samples per batch at most: bounds the work one (possibly forged) message can cause
MAX_BATCH: Final = 1024

KIND_HEARTBEAT: Final = 1
KIND_ACKNACK: Final = 2
KIND_GAP: Final = 3
#: an ACKNACK followed by the fragments missing from samples partly received
KIND_ACKNACK_FRAG: Final = 4

# HEARTBEAT: version, kind, flags, writer guid, first seq held, last seq written, count.
HEARTBEAT: Final = struct.Struct("!BBB8sQQI")
HB_FINAL: Final = 0x01
HB_LIVELINESS: Final = 0x02
HB_UNCHANGED: Final = 0x04
HB_SYNC: Final = 0x08

# ACKNACK: version, kind, reader guid, writer guid, base, count, number of ranges; then ranges.
ACKNACK: Final = struct.Struct("!BB8s8sQIH")
# GAP: version, kind, writer guid, reader guid, number of ranges; then ranges.
GAP: Final = struct.Struct("!BB8s8sH")
RANGE: Final = struct.Struct("!QQ")
# ACKNACK_FRAG's tail, after the ACKNACK's ranges: the number of fragment ranges, then each as
# (seq, first index, last index), inclusive
FRAG_COUNT: Final = struct.Struct("!H")
FRAG_RANGE: Final = struct.Struct("!QII")
#: fragment ranges per ACKNACK_FRAG: with 64 seq ranges the message still fits one datagram
#: in most cases, and a forged one asks for a bounded amount of work
MAX_FRAG_RANGES: Final = 32
#: ranges per ACKNACK or GAP: bounds the work a forged message can cause
MAX_RANGES: Final = 64
MAX_SEQ: Final = (1 << 63) - 1
#: the fastest a writer can produce seqs (samples per second; arpz's batched writer manages a few
#: hundred thousand): a seq further past the highest one known than this rate over the time since
#: the writer was last heard (plus one window) cannot be the writer's own, and is refused as bad
#: input instead of counted as loss. An outage of T seconds still allows a jump of T * this rate
MAX_WRITE_RATE_HZ: Final = 1_000_000

GUID_BYTES: Final = 8
REL: Final = "rel"


class DataHeader(NamedTuple):
    flags: int
    writer: bytes
    seq: int
    stamp_ns: int
    #: the count of the ACKNACK a resend answers; -1 in a DATA header
    echo: int = -1


class Heartbeat(NamedTuple):
    flags: int
    writer: bytes
    first: int
    last: int
    counter: int


class AckNack(NamedTuple):
    reader: bytes
    writer: bytes
    base: int
    counter: int
    missing: list[tuple[int, int]]
    #: (seq, first index, last index): fragments missing from samples received in part
    frags: tuple[tuple[int, int, int], ...] = ()


class FragHeader(NamedTuple):
    flags: int
    writer: bytes
    seq: int
    stamp_ns: int
    #: the fragment's index in its sample (0, 1, ...)
    fragment: int
    total: int
    chunk: int
    #: the count of the ACKNACK a resent fragment answers; -1 in a DATA_FRAG
    echo: int = -1


class Gap(NamedTuple):
    writer: bytes
    reader: bytes
    lost: list[tuple[int, int]]


def encode_data(flags: int, writer: bytes, seq: int, stamp_ns: int) -> bytes:
    return DATA.pack(VERSION, flags, writer, seq, stamp_ns)


def encode_resend(writer: bytes, seq: int, stamp_ns: int, echo: int) -> bytes:
    return RESEND.pack(VERSION, F_RETRANSMIT, writer, seq, stamp_ns, echo & 0xFFFFFFFF)


def encode_data_frag(
    flags: int, writer: bytes, seq: int, stamp_ns: int, index: int, total: int, chunk: int
) -> bytes:
    return DATA_FRAG.pack(VERSION, flags | F_FRAGMENT, writer, seq, stamp_ns, index, total, chunk)


def encode_resend_frag(
    writer: bytes, seq: int, stamp_ns: int, index: int, total: int, chunk: int, echo: int
) -> bytes:
    flags = F_RETRANSMIT | F_FRAGMENT
    return RESEND_FRAG.pack(
        VERSION, flags, writer, seq, stamp_ns, index, total, chunk, echo & 0xFFFFFFFF
    )


def decode_frag(attachment: bytes) -> FragHeader | None:
    """A DATA_FRAG header or a resent fragment's; None unless it describes a sample of at least
    two fragments and an index within it (the payload's length is the reader's to check)."""
    echo = -1
    if len(attachment) == DATA_FRAG.size:
        version, flags, writer, seq, stamp, index, total, chunk = DATA_FRAG.unpack(attachment)
    elif len(attachment) == RESEND_FRAG.size:
        version, flags, writer, seq, stamp, index, total, chunk, echo = RESEND_FRAG.unpack(
            attachment
        )
        if not flags & F_RETRANSMIT:
            return None
    else:
        return None
    if version != VERSION or not flags & F_FRAGMENT or seq < 1 or seq > MAX_SEQ:
        return None
    if chunk < 1 or total <= chunk or index * chunk >= total:
        return None
    return FragHeader(flags, writer, seq, stamp, index, total, chunk, echo)


def decode_data(attachment: bytes | None) -> DataHeader | None:
    """A DATA header, or a resend's (DATA and the ACKNACK count it answers)."""
    if attachment is None:
        return None
    if len(attachment) == DATA.size:
        version, flags, writer, seq, stamp = DATA.unpack(attachment)
        echo = -1
    elif len(attachment) == RESEND.size:
        version, flags, writer, seq, stamp, echo = RESEND.unpack(attachment)
        if not flags & F_RETRANSMIT:
            return None
    else:
        return None
    if version != VERSION or seq < 1 or seq > MAX_SEQ:
        return None
    return DataHeader(flags, writer, seq, stamp, echo)


class Batch(NamedTuple):
    flags: int
    writer: bytes
    first: int
    #: source stamp and payload of each sample, seq first, first + 1, ...
    stamps: tuple[int, ...]
    payloads: list[bytes]


@functools.cache
def _batch_entries(n: int) -> struct.Struct:
    return struct.Struct(f"!{n}q{n}I")


def encode_batch(
    flags: int, writer: bytes, first: int, payloads: list[bytes], stamps: list[int]
) -> tuple[bytes, bytes]:
    """(payload, attachment) of one message carrying ``payloads`` stamped ``stamps``."""
    n = len(payloads)
    head = BATCH.pack(VERSION, flags | F_BATCH, writer, first, n)
    return b"".join(payloads), head + _batch_entries(n).pack(*stamps, *map(len, payloads))


def decode_batch(payload: bytes, attachment: bytes) -> Batch | None:
    """None unless every length adds up exactly and every seq is valid."""
    if len(attachment) < BATCH.size:
        return None
    version, flags, writer, first, n = BATCH.unpack_from(attachment)
    if (
        version != VERSION
        or not flags & F_BATCH
        or not 1 <= n <= MAX_BATCH
        or len(attachment) != BATCH.size + n * BATCH_ENTRY_SIZE
        or first < 1
        or first + n - 1 > MAX_SEQ
    ):
        return None
    fields = _batch_entries(n).unpack_from(attachment, BATCH.size)
    lengths = fields[n:]
    size = lengths[0]
    if lengths.count(size) == n:
        # the common case (a topic of fixed-size samples): one cached struct cuts every
        # payload in C instead of a Python slice per sample
        if n * size != len(payload):
            return None
        payloads = list(_uniform_split(n, size).unpack(payload))
    else:
        ends = list(itertools.accumulate(lengths))
        # lengths are unsigned, so if they add up to the payload no slice runs past its end
        if ends[-1] != len(payload):
            return None
        payloads = [payload[start:end] for start, end in zip([0, *ends[:-1]], ends, strict=True)]
    return Batch(flags, writer, first, fields[:n], payloads)


@functools.lru_cache(maxsize=256)
def _uniform_split(n: int, size: int) -> struct.Struct:
    return struct.Struct(f"{size}s" * n)


def encode_heartbeat(flags: int, writer: bytes, first: int, last: int, count: int) -> bytes:
    return HEARTBEAT.pack(VERSION, KIND_HEARTBEAT, flags, writer, first, last, count & 0xFFFFFFFF)


def decode_heartbeat(payload: bytes) -> Heartbeat | None:
    if len(payload) != HEARTBEAT.size:
        return None
    version, kind, flags, writer, first, last, count = HEARTBEAT.unpack(payload)
    if version != VERSION or kind != KIND_HEARTBEAT or first < 1 or last > MAX_SEQ:
        return None
    if first > last + 1:
        return None
    return Heartbeat(flags, writer, first, last, count)


def _pack_ranges(ranges: list[tuple[int, int]]) -> bytes:
    return b"".join(RANGE.pack(lo, hi) for lo, hi in ranges[:MAX_RANGES])


def _unpack_ranges(payload: bytes, offset: int, n: int) -> list[tuple[int, int]] | None:
    if n > MAX_RANGES or len(payload) != offset + n * RANGE.size:
        return None
    ranges = [RANGE.unpack_from(payload, offset + i * RANGE.size) for i in range(n)]
    if any(lo < 1 or hi < lo or hi > MAX_SEQ for lo, hi in ranges):
        return None
    return ranges


def encode_acknack(
    reader: bytes,
    writer: bytes,
    base: int,
    count: int,
    missing: list[tuple[int, int]],
    frags: Sequence[tuple[int, int, int]] = (),
) -> bytes:
    """An ACKNACK; with ``frags`` (seq, first index, last index) an ACKNACK_FRAG, which asks
    for those fragments too."""
    n = min(len(missing), MAX_RANGES)
    kind = KIND_ACKNACK_FRAG if frags else KIND_ACKNACK
    head = ACKNACK.pack(VERSION, kind, reader, writer, base, count & 0xFFFFFFFF, n)
    if not frags:
        return head + _pack_ranges(missing)
    frags = frags[:MAX_FRAG_RANGES]
    tail = b"".join(FRAG_RANGE.pack(*f) for f in frags)
    return head + _pack_ranges(missing) + FRAG_COUNT.pack(len(frags)) + tail


def decode_acknack(payload: bytes) -> AckNack | None:
    if len(payload) < ACKNACK.size:
        return None
    version, kind, reader, writer, base, count, n = ACKNACK.unpack_from(payload)
    if version != VERSION or base < 1 or base > MAX_SEQ:
        return None
    if kind == KIND_ACKNACK_FRAG:
        return _decode_acknack_frag(payload, reader, writer, base, count, n)
    if kind != KIND_ACKNACK:
        return None
    ranges = _unpack_ranges(payload, ACKNACK.size, n)
    if ranges is None:
        return None
    return AckNack(reader, writer, base, count, ranges)


def _decode_acknack_frag(
    payload: bytes, reader: bytes, writer: bytes, base: int, count: int, n: int
) -> AckNack | None:
    at = ACKNACK.size + n * RANGE.size
    if n > MAX_RANGES or len(payload) < at + FRAG_COUNT.size:
        return None
    ranges = _unpack_ranges(payload[:at], ACKNACK.size, n)
    (m,) = FRAG_COUNT.unpack_from(payload, at)
    at += FRAG_COUNT.size
    if ranges is None or not 1 <= m <= MAX_FRAG_RANGES or len(payload) != at + m * FRAG_RANGE.size:
        return None
    frags = tuple(FRAG_RANGE.unpack_from(payload, at + i * FRAG_RANGE.size) for i in range(m))
    if any(seq < 1 or seq > MAX_SEQ or hi < lo for seq, lo, hi in frags):
        return None
    return AckNack(reader, writer, base, count, ranges, frags)


def encode_gap(writer: bytes, reader: bytes, lost: list[tuple[int, int]]) -> bytes:
    n = min(len(lost), MAX_RANGES)
    return GAP.pack(VERSION, KIND_GAP, writer, reader, n) + _pack_ranges(lost)


def decode_gap(payload: bytes) -> Gap | None:
    if len(payload) < GAP.size:
        return None
    version, kind, writer, reader, n = GAP.unpack_from(payload)
    if version != VERSION or kind != KIND_GAP:
        return None
    ranges = _unpack_ranges(payload, GAP.size, n)
    if ranges is None:
        return None
    return Gap(writer, reader, ranges)


def control_kind(payload: bytes) -> int | None:
    if len(payload) < 2 or payload[0] != VERSION:
        return None
    return payload[1]


def to_ranges(seqs: list[int]) -> list[tuple[int, int]]:
    """Sorted distinct seqs -> inclusive runs, so long gaps cost one range, not one entry each."""
    ranges: list[tuple[int, int]] = []
    for seq in seqs:
        if ranges and ranges[-1][1] + 1 == seq:
            ranges[-1] = (ranges[-1][0], seq)
        else:
            ranges.append((seq, seq))
    return ranges


# ----------------------------------------------------------------------------------- keys
# Every control key has chunks below the topic key, so a subscriber of ``.../sensor/*`` or
# ``.../cmd/*`` (single-chunk wildcard) never sees control traffic.


def writer_token(topic: str, writer: str, qos_chunk: str) -> str:
    return f"{topic}/{REL}/w/{writer}/{qos_chunk}"


def reader_token(topic: str, reader: str, qos_chunk: str) -> str:
    return f"{topic}/{REL}/r/{reader}/{qos_chunk}"


def heartbeat_key(topic: str, writer: str) -> str:
    return f"{topic}/{REL}/hb/{writer}"


def acknack_key(topic: str, writer: str, reader: str) -> str:
    return f"{topic}/{REL}/an/{writer}/{reader}"


def directed_key(topic: str, reader: str) -> str:
    """Resends (with a DATA attachment), GAPs and SYNC heartbeats for one reader only, so one
    lossy reader never makes the others see duplicates."""
    return f"{topic}/{REL}/rx/{reader}"


def split_control_key(key: str, kind: str, n_after: int) -> tuple[str, list[str]] | None:
    """``{topic}/rel/{kind}/{a}[/{b}]`` -> (topic, [a, b]); None if the key has another shape."""
    parts = key.split("/")
    at = len(parts) - n_after - 2
    if at < 1 or parts[at] != REL or parts[at + 1] != kind:
        return None
    return "/".join(parts[:at]), parts[at + 2 :]


def check_topic_key(key: str) -> str:
    """A writer's key must be concrete and must not contain a ``rel`` chunk (reserved above)."""
    parts = key.split("/")
    if not key or any(not p or p in ("*", "**") or "$" in p or "?" in p or "#" in p for p in parts):
        raise ValueError(
            f"writer key {key!r} must be a concrete Zenoh key (no wildcards, no empty chunk)"
        )
    if REL in parts:
        raise ValueError(
            f"writer key {key!r} must not contain the chunk {REL!r} (reserved for control)"
        )
    return key


def check_key_expr(key_expr: str) -> str:
    parts = key_expr.split("/")
    if not key_expr or any(not p for p in parts):
        raise ValueError(f"reader key expression {key_expr!r} has an empty chunk")
    if REL in parts:
        raise ValueError(f"reader key expression {key_expr!r} must not contain the chunk {REL!r}")
    return key_expr
