"""Clock offset between a robot and the CEDDP: the NTP exchange's arithmetic, pure.

A robot sends a request at t1 (its clock), the CEDDP receives it at t2 and replies at t3 (the
CEDDP's clock), the robot receives the reply at t4 (its clock). With equal one-way delays,

    offset = ((t2 - t1) + (t3 - t4)) / 2      the CEDDP's clock minus the robot's
    delay  = (t4 - t1) - (t3 - t2)            the round trip, less the CEDDP's own time

and when the two directions differ the error of ``offset`` is at most ``delay / 2`` (the
whole asymmetry on one side). The exchange with the smallest delay is the one least disturbed
by queues, so ``MinDelayFilter`` keeps the last N exchanges and reports the offset of the
fastest (the NTP clock filter's rule). A robot stamp corrected to the CEDDP's clock is
``stamp_ns + offset_ns``; a latency measured at the CEDDP is ``arrival - stamp - offset``.

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


@dataclass(frozen=True, slots=True)
class Estimate:
    """The filter's answer: the offset and delay of the fastest recent exchange."""

    offset_ns: int
    delay_ns: int
    #: exchanges the filter holds (the estimate is the best of them)
    samples: int
    #: the robot's clock at the end of the chosen exchange (its t4)
    stamp_ns: int

    @property
    def error_bound_ns(self) -> int:
        """How far ``offset_ns`` can be from the truth, whatever the asymmetry: delay / 2."""
        return (self.delay_ns + 1) // 2


class MinDelayFilter:
    """The last ``window`` plausible exchanges; the estimate is the one with the least delay.

    Implausible exchanges are counted in ``refused`` and never kept."""

    def __init__(self, window: int) -> None:
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        self._exchanges: deque[Exchange] = deque(maxlen=window)
        self.refused = 0

    def add(self, exchange: Exchange) -> bool:
        """Keep ``exchange`` if plausible; returns whether it was kept."""
        if not exchange.plausible:
            self.refused += 1
            return False
        self._exchanges.append(exchange)
        return True

    def estimate(self) -> Estimate | None:
        """None before the first plausible exchange."""
        if not self._exchanges:
            return None
        best = min(self._exchanges, key=lambda e: e.delay_ns)
        return Estimate(best.offset_ns, best.delay_ns, len(self._exchanges), best.t4_ns)


def corrected_latency_ms(arrival_ns: int, stamp_ns: int, offset_ns: int) -> float:
    """A latency measured on the CEDDP's clock from a robot's stamp, the offset taken out."""
    return (arrival_ns - stamp_ns - offset_ns) / 1e6
