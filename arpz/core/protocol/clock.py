"""Clock offset between a robot and the CEDDP: the NTP exchange's arithmetic, pure.

A robot sends a request at t1 (its clock), the CEDDP receives it at t2 and replies at t3 (the
CEDDP's clock), the robot receives the reply at t4 (its clock). With equal one-way delays,

    offset = ((t2 - t1) + (t3 - t4)) / 2      the CEDDP's clock minus the robot's
    delay  = (t4 - t1) - (t3 - t2)            the round trip, less the CEDDP's own time

and when the two directions differ the error of ``offset`` is at most ``delay / 2`` (the
whole asymmetry on one side). The exchange with the smallest delay is the one least disturbed
by queues. A window of the last N alone is not enough: on a saturated link, or over TCP where
lost frames become retransmission delay, every exchange of the window can wait 50-300 ms more
one way than the other, and its fastest is then off by half of that (issue 39: +50 to +274 ms
on one host, where the truth is 0). So ``MinDelayFilter`` also keeps the *floor*, the least
delay seen over the whole run (two integers, however long), and accepts an exchange only when
its delay is within ``margin_ns`` of it (NTP's clock filter, and the popcorn-spike suppression
of ntpd and chrony); the estimate is the fastest accepted exchange of the last N, and when none
of them was accepted the previous estimate is held. The floor rises by ``floor_rise_ns_per_s``
while nothing comes under it, so that a route whose round trip really grew is accepted in the
end (a route 10 ms longer after 8 minutes at the defaults: 10 ms less the margin, at 1 ms a
minute).

The guarantee: let the one-way delays be ``b + qu`` and ``b + qd`` (the same base both ways,
queueing ``qu``, ``qd`` >= 0, anything at all). An accepted exchange's delay is at most
floor + margin, and the floor is at most the delay of any exchange seen (plus its rise since),
so once one exchange with qu + qd <= eps has been seen, every estimate from then on is within
(eps + margin + rise) / 2 of the truth: within ``margin_ns`` (2 ms) with eps = margin and the
floor freshly set, however many exchanges in between were queued, and whichever side.
A robot stamp corrected to the CEDDP's clock is ``stamp_ns + offset_ns``; a latency measured at
the CEDDP is ``arrival - stamp - offset``.

No I/O here: the robot's ``arpz.robot.clock_sync`` does the exchanges over Zenoh, the CEDDP's
``arpz.ceddp.clock_service`` answers and applies the estimates.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Exchange:
    """One request/reply: t1 and t4 on the robot's clock, t2 and t3 on the CEDDP's (ns)."""

    t1_ns: int
    t2_ns: int
    t3_ns: int
    t4_ns: int

    @property
    def offset_ns(self) -> int:
        """The CEDDP's clock minus the robot's, exact when both directions take as long."""
        return ((self.t2_ns - self.t1_ns) + (self.t3_ns - self.t4_ns)) // 2

    @property
    def delay_ns(self) -> int:
        """The round trip on the wire: the robot's wait less the CEDDP's time holding it."""
        return (self.t4_ns - self.t1_ns) - (self.t3_ns - self.t2_ns)

    @property
    def plausible(self) -> bool:
        """False for an exchange no pair of clocks can produce (a reply before its request on
        the robot's clock, or a CEDDP that replied before it received): a clock stepped
        during the exchange, or a forged reply. It must not become an estimate."""
        return self.t4_ns >= self.t1_ns and self.t3_ns >= self.t2_ns and self.delay_ns >= 0


#: an exchange is accepted when its delay is within this of the floor: its queueing, on both
#: sides together, is then at most this much more than the floor's, its offset off by at most
#: half of it (1 ms) more than the floor exchange's
MARGIN_NS = 2_000_000
#: how fast the floor rises while no exchange comes under it: 1 ms a minute. A route whose
#: round trip grew by D is accepted after D - margin at this rate (10 ms: 8 minutes); a spell
#: queued 50 ms above the floor would have to last 48 minutes to be taken for one
FLOOR_RISE_NS_PER_S = 16_667


@dataclass(frozen=True, slots=True)
class Estimate:
    """The filter's answer: the offset and delay of the fastest recent accepted exchange."""

    offset_ns: int
    delay_ns: int
    #: accepted exchanges of the window when it was chosen (the estimate is the best of them)
    samples: int
    #: the robot's clock at the end of the chosen exchange (its t4)
    stamp_ns: int

    @property
    def error_bound_ns(self) -> int:
        """How far ``offset_ns`` can be from the truth, whatever the asymmetry: delay / 2."""
        return (self.delay_ns + 1) // 2


class MinDelayFilter:
    """The last ``window`` plausible exchanges, each accepted or refused against the floor (the
    least delay seen, risen by ``floor_rise_ns_per_s`` since: ``floor_ns``) when it came; the
    estimate is the accepted one with the least delay, or the previous estimate while the
    window holds no accepted exchange. Bounded: the window, the floor and the estimate.

    Implausible exchanges are counted in ``refused`` and never kept; plausible ones too slow
    to be accepted are kept (they count in the window) and counted in ``rejected``."""

    def __init__(
        self,
        window: int,
        *,
        margin_ns: int = MARGIN_NS,
        floor_rise_ns_per_s: int = FLOOR_RISE_NS_PER_S,
    ) -> None:
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        if margin_ns < 0 or floor_rise_ns_per_s < 0:
            raise ValueError(
                f"margin_ns and floor_rise_ns_per_s must be >= 0, got {margin_ns} and "
                f"{floor_rise_ns_per_s}"
            )
        self.margin_ns = margin_ns
        self.floor_rise_ns_per_s = floor_rise_ns_per_s
        #: (exchange, accepted when it came)
        self._exchanges: deque[tuple[Exchange, bool]] = deque(maxlen=window)
        #: the least delay seen, and when (the caller's clock: ``add``'s ``now_ns``)
        self._floor: tuple[int, int] | None = None
        self._estimate: Estimate | None = None
        self.refused = 0
        self.accepted = 0
        self.rejected = 0

    def floor_ns(self, now_ns: int) -> int | None:
        """The least delay seen, risen since at ``floor_rise_ns_per_s`` (None before any)."""
        if self._floor is None:
            return None
        least, at_ns = self._floor
        return least + max(0, now_ns - at_ns) * self.floor_rise_ns_per_s // 1_000_000_000

    def add(self, exchange: Exchange, now_ns: int | None = None) -> bool:
        """Keep ``exchange`` if plausible; returns whether it was kept (accepted or not: see
        ``accepted``). ``now_ns``: a monotonic clock for the floor's rise (default: the
        exchange's t4, the robot's wall clock)."""
        if not exchange.plausible:
            self.refused += 1
            return False
        now = exchange.t4_ns if now_ns is None else now_ns
        floor = self.floor_ns(now)
        if floor is None or exchange.delay_ns <= floor:
            self._floor = (exchange.delay_ns, now)
            floor = exchange.delay_ns
        accepted = exchange.delay_ns <= floor + self.margin_ns
        if accepted:
            self.accepted += 1
        else:
            self.rejected += 1
        self._exchanges.append((exchange, accepted))
        candidates = [e for e, ok in self._exchanges if ok]
        if candidates:
            best = min(candidates, key=lambda e: e.delay_ns)
            self._estimate = Estimate(best.offset_ns, best.delay_ns, len(candidates), best.t4_ns)
        return True

    def estimate(self) -> Estimate | None:
        """None before the first plausible exchange (which is always accepted)."""
        return self._estimate


def corrected_latency_ms(arrival_ns: int, stamp_ns: int, offset_ns: int) -> float:
    """A latency measured on the CEDDP's clock from a robot's stamp, the offset taken out."""
    return (arrival_ns - stamp_ns - offset_ns) / 1e6
