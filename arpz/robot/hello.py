"""Bookkeeping of the Hello round trips at the origin robot (seed 001 Fig. 9).

A Hello is outstanding from the moment it is sent until it comes back (a round trip) or
``timeout_s`` passes (lost). A Hello that comes back after it was declared lost, or twice, is
counted as late, never as a second round trip. Pure logic, thread-safe.
"""

from __future__ import annotations

import threading

from arpz.messages import HelloStats
from arpz.percentiles import Distribution


class HelloTracker:
    def __init__(self, timeout_s: float) -> None:
        self.timeout_ns = int(timeout_s * 1e9)
        self._lock = threading.Lock()
        self._outstanding: dict[int, int] = {}
        self.sent = 0
        self.received = 0
        self.lost = 0
        self.late = 0
        self.relayed = 0
        self.rtt_ms = Distribution()

    def on_sent(self, origin_seq: int, t0_ns: int) -> None:
        with self._lock:
            self.sent += 1
            self._outstanding[origin_seq] = t0_ns

    def on_returned(self, origin_seq: int, now_ns: int) -> float | None:
        """Record a Hello that came back; returns its round trip in ms, or None if late."""
        with self._lock:
            t0_ns = self._outstanding.pop(origin_seq, None)
            if t0_ns is None:
                self.late += 1
                return None
            self.received += 1
            rtt_ms = (now_ns - t0_ns) / 1e6
            self.rtt_ms.add(rtt_ms)
            return rtt_ms

    def on_relayed(self) -> None:
        with self._lock:
            self.relayed += 1

    def expire(self, now_ns: int, *, all_outstanding: bool = False) -> int:
        """Declare lost every Hello older than the timeout (or every one, at shutdown)."""
        with self._lock:
            gone = [
                seq
                for seq, t0 in self._outstanding.items()
                if all_outstanding or now_ns - t0 >= self.timeout_ns
            ]
            for seq in gone:
                del self._outstanding[seq]
            self.lost += len(gone)
            return len(gone)

    @property
    def outstanding(self) -> int:
        with self._lock:
            return len(self._outstanding)

    def stats(self) -> HelloStats:
        with self._lock:
            return HelloStats(
                sent=self.sent,
                received=self.received,
                lost=self.lost,
                outstanding=len(self._outstanding),
                relayed=self.relayed,
                late=self.late,
                rtt_ms_p50=self.rtt_ms.quantile(50),
                rtt_ms_p99=self.rtt_ms.quantile(99),
                rtt_ms_max=self.rtt_ms.max,
            )
