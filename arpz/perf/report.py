"""What a subscriber measured, reduced to the report ``sub --json`` writes. Pure: no I/O.

Fields follow Apex.AI performance_test (sent/received/lost, latency statistics) and iRobot
ros2-performance (``late`` and ``too_late``), so figures compare with what the ROS 2 community
publishes.
"""

from __future__ import annotations

import itertools
import math
import struct
import threading
from array import array
from collections.abc import Callable
from typing import Final

import msgspec

#: every perf payload starts with (seq, source stamp in ns), whatever the transport
HEADER: Final = struct.Struct("!Qq")
#: a source stamp further than this from the receiver's clock is not a perf sample's
PLAUSIBLE_STAMP_NS: Final = 86_400 * 10**9


def make_payload(seq: int, stamp_ns: int, size: int) -> bytes:
    return payload_maker(size)(seq, stamp_ns)


def payload_maker(size: int) -> Callable[[int, int], bytes]:
    """(seq, stamp_ns) -> payload of ``size`` bytes (at least the header). The padding is made
    once: the publishing loop is the tool's own overhead, the same for every transport, and
    allocating a fresh kilobyte per sample cost half a microsecond of it."""
    padding = bytes(max(0, size - HEADER.size))
    pack = HEADER.pack

    def make(seq: int, stamp_ns: int) -> bytes:
        return pack(seq, stamp_ns) + padding

    return make


class LatencyUs(msgspec.Struct, frozen=True):
    min: float
    p50: float
    p90: float
    p99: float
    max: float
    mean: float


class Report(msgspec.Struct, frozen=True):
    transport: str
    key: str
    size: int
    rate_hz: float
    #: as known from the writer's sequence numbers (its end marker, else the highest seen)
    sent: int
    received: int
    #: reported by the channel (arpz: MESSAGE_LOST; advanced: miss listener; zenoh: nothing)
    lost: int
    #: sent - received - lost: samples that vanished without anyone saying so
    unaccounted: int
    duplicates: int
    out_of_order: int
    latency_us: LatencyUs | None
    throughput_msg_s: float
    retransmissions: int
    nacks: int
    longest_stall_ms: float
    #: latency > min(0.2 period, 5 ms) (iRobot); too_late: > min(period, 50 ms)
    late: int
    too_late: int
    duration_s: float
    #: payloads on the key that were not perf samples (too short, or an impossible seq or
    #: stamp): someone else publishes there, e.g. a robot's sensors; not in any figure above
    foreign: int = 0


def percentile(sorted_values: list[float], q: float) -> float:
    """Nearest-rank percentile of an already sorted list (q in [0, 100])."""
    if not sorted_values:
        return 0.0
    rank = math.ceil(q / 100 * len(sorted_values)) - 1
    return sorted_values[max(0, min(len(sorted_values) - 1, rank))]


class Recorder:
    """Appends (seq, latency, arrival) from the receiving thread; cheap enough for 300 k msg/s."""

    def __init__(self) -> None:
        self.seqs = array("q")
        self.latency_ns = array("q")
        self.arrival_s = array("d")
        self.lock = threading.Lock()
        self.foreign = 0

    def add(self, seq: int, latency_ns: int, arrival_s: float) -> None:
        with self.lock:
            self.seqs.append(seq)
            self.latency_ns.append(latency_ns)
            self.arrival_s.append(arrival_s)

    def add_payload(self, payload: bytes, now_ns: int, now_s: float) -> bool:
        """Record a perf sample received at ``now_ns`` (wall) / ``now_s`` (monotonic). Anything
        else is counted in ``foreign`` and skipped: pointed at a robot's keys, the subscriber
        read its sensor bytes as seqs beyond int64 and raised on every sample."""
        if len(payload) >= HEADER.size:
            seq, stamp = HEADER.unpack_from(payload)
            if 0 < seq < 2**63 and abs(now_ns - stamp) < PLAUSIBLE_STAMP_NS:
                self.add(seq, now_ns - stamp, now_s)
                return True
        with self.lock:
            self.foreign += 1
        return False

    def __len__(self) -> int:
        return len(self.seqs)


def build_report(
    rec: Recorder,
    *,
    transport: str,
    key: str,
    size: int,
    rate_hz: float,
    sent: int | None,
    lost: int,
    retransmissions: int,
    nacks: int,
    duration_s: float,
) -> Report:
    with rec.lock:
        seqs = list(rec.seqs)
        lat_us = [v / 1000 for v in rec.latency_ns]
        arrival = list(rec.arrival_s)
        foreign = rec.foreign
    seen: set[int] = set()
    duplicates = out_of_order = 0
    highest = 0
    for seq in seqs:
        if seq in seen:
            duplicates += 1
            continue
        seen.add(seq)
        if seq < highest:
            out_of_order += 1
        highest = max(highest, seq)
    received = len(seen)
    sent_n = sent if sent is not None else highest
    period_s = 1.0 / rate_hz if rate_hz > 0 else 0.0
    late_us = 1e6 * (min(0.2 * period_s, 0.005) if period_s else 0.005)
    too_late_us = 1e6 * (min(period_s, 0.05) if period_s else 0.05)
    stall_s = max((b - a for a, b in itertools.pairwise(arrival)), default=0.0)
    span_s = arrival[-1] - arrival[0] if len(arrival) > 1 else 0.0
    latency = None
    if lat_us:
        ordered = sorted(lat_us)
        latency = LatencyUs(
            min=ordered[0],
            p50=percentile(ordered, 50),
            p90=percentile(ordered, 90),
            p99=percentile(ordered, 99),
            max=ordered[-1],
            mean=sum(ordered) / len(ordered),
        )
    return Report(
        transport=transport,
        key=key,
        size=size,
        rate_hz=rate_hz,
        sent=sent_n,
        received=received,
        lost=lost,
        unaccounted=max(0, sent_n - received - lost),
        duplicates=duplicates,
        out_of_order=out_of_order,
        latency_us=latency,
        throughput_msg_s=(len(seqs) - 1) / span_s if span_s > 0 else 0.0,
        retransmissions=retransmissions,
        nacks=nacks,
        longest_stall_ms=stall_s * 1000,
        late=sum(1 for v in lat_us if v > late_us),
        too_late=sum(1 for v in lat_us if v > too_late_us),
        duration_s=duration_s,
        foreign=foreign,
    )
