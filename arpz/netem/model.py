"""The impairment model of the lossy-link emulator, pure: a datagram in, a fate out.

Kept apart from sockets so the statistics (loss rate, burst lengths, bandwidth) are unit-tested
with a seeded RNG and a given time, and the proxy only carries out the decisions.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass, field

#: bytes of an IPv4 header (without options) and of a UDP header: a UDP payload of n bytes is an
#: IP packet of n + 28 bytes, and each IP fragment carries its own 20-byte IP header
IP_HEADER_BYTES = 20
UDP_HEADER_BYTES = 8
#: the Ethernet/WiFi MTU: the largest IP packet one radio frame carries
WIFI_MTU_BYTES = 1500


def frames_of(size: int, frame_bytes: int = WIFI_MTU_BYTES) -> int:
    """Radio frames a UDP datagram with ``size`` payload bytes takes once IP fragments it for an
    MTU of ``frame_bytes``: its UDP header and payload split into pieces of ``frame_bytes`` - 20
    bytes (rounded down to 8, as IP fragment offsets are), each behind its own IP header. A
    1472-byte payload is one frame, 1473 bytes are two, an 8 KiB datagram six."""
    per_frame = (frame_bytes - IP_HEADER_BYTES) // 8 * 8
    return max(1, math.ceil((size + UDP_HEADER_BYTES) / per_frame))


@dataclass(frozen=True, kw_only=True)
class GilbertElliott:
    """Two-state bursty loss: Good -> Bad with probability ``p`` per datagram, Bad -> Good with
    ``r``; loss probability ``loss_good`` in Good and ``loss_bad`` in Bad. The mean burst length
    is 1 / r and the long-run loss rate (p*loss_bad + r*loss_good) / (p + r)."""

    p: float
    r: float
    loss_good: float = 0.0
    loss_bad: float = 1.0

    def __post_init__(self) -> None:
        for name in ("p", "r", "loss_good", "loss_bad"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"Gilbert-Elliott {name} must be within [0, 1], got {value}")
        if self.r == 0.0:
            raise ValueError("Gilbert-Elliott r must be > 0 or the link never leaves the bad state")

    @property
    def mean_loss(self) -> float:
        return (
            (self.p * self.loss_bad + self.r * self.loss_good) / (self.p + self.r)
            if self.p + self.r
            else self.loss_good
        )


@dataclass(frozen=True, kw_only=True)
class Outage:
    """Everything dropped from ``start_s`` (after the clean period) for ``duration_s``."""

    start_s: float
    duration_s: float


@dataclass(frozen=True, kw_only=True)
class Impairments:
    loss: float = 0.0
    burst: GilbertElliott | None = None
    delay_s: float = 0.0
    jitter_s: float = 0.0
    #: bits per second; 0 = unlimited
    rate_bps: float = 0.0
    #: longest a datagram may wait behind the bandwidth cap before it is dropped (tail drop)
    queue_limit_s: float = 0.5
    duplicate: float = 0.0
    #: fraction of datagrams held back an extra ``reorder_gap_s`` so later ones overtake them
    reorder: float = 0.0
    reorder_gap_s: float = 0.005
    outages: tuple[Outage, ...] = ()
    #: the first seconds are clean so the Zenoh session can establish over the link
    clean_s: float = 0.0
    #: ``loss`` applies to each radio frame of ``frame_bytes`` (the MTU), not to each datagram: a
    #: datagram IP fragments into k frames survives with probability (1 - loss)^k, as on a real
    #: radio, where losing one fragment loses the whole datagram. Off by default so that the
    #: existing profiles and their figures (small datagrams, loss per datagram) keep their meaning;
    #: large-payload tests and benchmarks turn it on (docs/netem.md)
    per_frame: bool = False
    frame_bytes: int = WIFI_MTU_BYTES

    def __post_init__(self) -> None:
        for name in ("loss", "duplicate", "reorder"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} must be a fraction within [0, 1], got {value}")
        for name in (
            "delay_s",
            "jitter_s",
            "rate_bps",
            "queue_limit_s",
            "reorder_gap_s",
            "clean_s",
        ):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.frame_bytes < 68:  # the smallest MTU IPv4 allows
            raise ValueError(f"frame_bytes must be >= 68 (an IPv4 MTU), got {self.frame_bytes}")


@dataclass
class Counters:
    received: int = 0
    forwarded: int = 0
    dropped_loss: int = 0
    dropped_burst: int = 0
    dropped_outage: int = 0
    dropped_queue: int = 0
    duplicated: int = 0
    reordered: int = 0
    #: UDP payload bytes received from the sender and sent on to the receiver (copies included):
    #: what really crossed the emulated link, e.g. to check that a large payload did not take
    #: Zenoh's shared-memory path around it
    bytes_in: int = 0
    bytes_out: int = 0
    #: radio frames the received datagrams take at the MTU (``frames_of``), whatever ``per_frame``
    frames_in: int = 0
    #: the largest datagram received (UDP payload bytes): shows whether Zenoh's batches stay
    #: within one frame
    largest_datagram: int = 0
    #: decided forwarded, but the socket refused it (full buffer, vanished peer)
    send_errors: int = 0
    #: datagrams the kernel dropped before the proxy read them (its receive buffer was full: a
    #: burst faster than the proxy), from /proc/net/udp; not part of ``received``. Not emulated
    #: loss: a run where it is not 0 measured the emulator's limit, and says so
    rx_overflow: int = 0

    @property
    def dropped(self) -> int:
        return (
            self.dropped_loss
            + self.dropped_burst
            + self.dropped_outage
            + self.dropped_queue
            + self.send_errors
        )


@dataclass
class Direction:
    """One direction of the link: its own burst state and bandwidth queue."""

    imp: Impairments
    rng: random.Random
    counters: Counters = field(default_factory=Counters)
    _bad: bool = False
    _link_free_s: float = 0.0

    def fate(self, size: int, elapsed_s: float, now_s: float) -> list[float]:
        """Departure times of the copies of one datagram (empty: dropped). ``elapsed_s`` is the
        time since the link started (outages and clean period), ``now_s`` the scheduler's clock."""
        c, imp, rng = self.counters, self.imp, self.rng
        c.received += 1
        c.bytes_in += size
        frames = frames_of(size, imp.frame_bytes)
        c.frames_in += frames
        c.largest_datagram = max(c.largest_datagram, size)
        if elapsed_s >= imp.clean_s:
            t = elapsed_s - imp.clean_s
            if any(o.start_s <= t < o.start_s + o.duration_s for o in imp.outages):
                c.dropped_outage += 1
                return []
            if imp.burst is not None:
                ge = imp.burst
                self._bad = (rng.random() >= ge.r) if self._bad else (rng.random() < ge.p)
                if rng.random() < (ge.loss_bad if self._bad else ge.loss_good):
                    c.dropped_burst += 1
                    return []
            if imp.loss:
                # per frame: the datagram survives only if each of its frames does. One draw
                # against the combined probability, so per-datagram loss (and a one-frame
                # datagram) makes exactly the decisions it made before per-frame loss existed
                lose = imp.loss
                if imp.per_frame and frames > 1:
                    lose = 1 - (1 - imp.loss) ** frames
                if rng.random() < lose:
                    c.dropped_loss += 1
                    return []
        copies = 1
        if imp.duplicate and rng.random() < imp.duplicate:
            copies = 2
            c.duplicated += 1
        depart = now_s
        if imp.rate_bps > 0:
            start = max(now_s, self._link_free_s)
            if start - now_s > imp.queue_limit_s:
                c.dropped_queue += 1
                return []
            self._link_free_s = start + size * 8 / imp.rate_bps
            depart = self._link_free_s
        times = []
        for _ in range(copies):
            delay = imp.delay_s
            if imp.jitter_s:
                delay = max(0.0, delay + rng.uniform(-imp.jitter_s, imp.jitter_s))
            if imp.reorder and rng.random() < imp.reorder:
                delay += imp.reorder_gap_s
                c.reordered += 1
            times.append(depart + delay)
        c.forwarded += copies
        c.bytes_out += size * copies
        return times
