"""The Hello round trips at the robot (seed 001 Fig. 9): the probe that sends and relays hops,
and the bookkeeping at the origin.

A Hello is outstanding from the moment it is sent until it comes back (a round trip) or
``timeout_s`` passes (lost). A Hello that comes back after it was declared lost, or twice, is
counted as late, never as a second round trip. The tracker is pure logic, thread-safe.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import msgspec

from arpz.channel.io import Outlet
from arpz.core.messages import Hello, HelloStats, encode
from arpz.core.percentiles import Distribution

log = logging.getLogger(__name__)


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
        """Record a Hello that came back; returns its round trip in ms, or None if late.

        A Hello back after ``timeout_s`` is lost even when no ``expire`` ran in between (the
        periodic sweep, or the shutdown drain that waits for Hellos in flight): a round trip
        longer than the timeout must not count as one."""
        with self._lock:
            t0_ns = self._outstanding.pop(origin_seq, None)
            if t0_ns is None:
                self.late += 1
                return None
            if now_ns - t0_ns >= self.timeout_ns:
                self.lost += 1
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
            p50, p99 = self.rtt_ms.quantiles(50, 99)  # one fold for both
            return HelloStats(
                sent=self.sent,
                received=self.received,
                lost=self.lost,
                outstanding=len(self._outstanding),
                relayed=self.relayed,
                late=self.late,
                rtt_ms_p50=p50,
                rtt_ms_p99=p99,
                rtt_ms_max=self.rtt_ms.max,
            )


class HelloProbe:
    """The robot's end of the Hello round trip (seed 001 Fig. 9): it originates a Hello every
    period, relays a stage-1 hop as stage 2 (when the CEDDP picked this robot as the relay), and
    records a stage-3 hop of its own as a round trip. Every hop it puts goes out on the robot's
    ``sensor/hello`` outlet with a seq of its own (one count for originals and relays)."""

    def __init__(self, robot_id: str, writer: str, outlet: Outlet, timeout_s: float) -> None:
        self.robot_id = robot_id
        self.writer = writer
        self.outlet = outlet
        self.tracker = HelloTracker(timeout_s)
        self._lock = threading.Lock()
        self._origin_seq = 0
        self._writer_seq = 0
        #: the robot's wall clock (the agent's, which ``[clock] shift_s`` can shift)
        self.wall_ns: Callable[[], int] = time.time_ns

    def send(self, _now_s: float) -> None:
        """A scheduler job: originate one Hello, and expire the ones past their timeout."""
        with self._lock:
            self._origin_seq += 1
            origin_seq = self._origin_seq
        t0_ns = self.wall_ns()
        self.tracker.on_sent(origin_seq, t0_ns)
        self._put(Hello(self.writer, 0, 0, self.robot_id, origin_seq, t0_ns, 0))
        self.tracker.expire(self.wall_ns())

    def on_hop(self, hello: Hello) -> bool:
        """A hop from the CEDDP; False if it is no hop this robot should get (counted by the
        caller as a bad command)."""
        if hello.stage == 1:
            self.tracker.on_relayed()
            self._put(msgspec.structs.replace(hello, stage=2))
            return True
        if hello.stage == 3 and hello.origin == self.robot_id:
            self.tracker.on_returned(hello.origin_seq, self.wall_ns())
            return True
        log.warning("unexpected Hello stage %d from %s", hello.stage, hello.writer)
        return False

    def drain(self, timeout_s: float) -> None:
        """At shutdown: wait (bounded) for the Hellos in flight, then count the rest lost."""
        deadline = time.monotonic() + timeout_s
        while self.tracker.outstanding and time.monotonic() < deadline:
            time.sleep(0.01)
        self.tracker.expire(self.wall_ns(), all_outstanding=True)

    def _put(self, hello: Hello) -> None:
        with self._lock:
            self._writer_seq += 1
            seq = self._writer_seq
        stamped = msgspec.structs.replace(
            hello, writer=self.writer, seq=seq, stamp_ns=self.wall_ns()
        )
        self.outlet.send(encode(stamped), stamped.stamp_ns)
