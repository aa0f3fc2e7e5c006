"""The CEDDP's side of clock offsets: answer the robots' clock requests, apply their estimates.

``ClockService`` serves ``ceddp/clock``: each ``ClockRequest`` (the robot's t1) gets a
``ClockReply`` with t2 (received) and t3 (replying) on this CEDDP's clock, from the transport's
callback thread so that nothing but the reply's encoding sits between the two stamps.

``ClockWatch`` takes each robot's estimate from its reports (``RobotStats.clock``,
``Announce.clock``; on the control worker, under the ingest lock), hands the offset to the
ingest so that every latency and staleness of the robot is measured on this CEDDP's clock, and
flags a robot whose |offset| exceeds ``[clock] max_offset_ms`` whatever the exchange's asymmetry
(|offset| - delay / 2 beyond the bound): one WARN event when it crosses the bound, one INFO event
when it is back (|offset| + delay / 2 within it). The estimates come from the robot's filter,
which never takes a queued exchange over a fast one (arpz/core/protocol/clock.py); the error bound
keeps a robot's one slow first exchange, or an older robot's unfiltered estimate, from telling
the user to set up NTP on a robot whose clock is right. The summary, the dashboard's frames and
``CeddpStats`` say which offset was used for whom.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from arpz.ceddp.ingest import Ingest
from arpz.core import keys
from arpz.core.config import CeddpClockConfig
from arpz.core.messages import CLOCK_REQUEST_DECODER, DECODE_ERRORS, ClockReply, ClockStats, encode
from arpz.core.transport import Handle, Transport

#: (text, level) -> None: a fleet event, for the log, the dashboard and the summary
EventSink = Callable[[str, str], None]


class ClockService:
    """The queryable on ``ceddp/clock``."""

    def __init__(self, transport: Transport, fleet: str) -> None:
        self._transport = transport
        self.key = keys.ceddp_clock_key(fleet)
        self._handle: Handle | None = None
        self._lock = threading.Lock()
        #: requests answered, and requests that could not be decoded (not answered)
        self.answered = 0
        self.bad_requests = 0

    def start(self) -> None:
        self._handle = self._transport.serve(self.key, self.answer)

    def answer(self, payload: bytes) -> bytes | None:
        """On the transport's thread: t2 first, t3 last, nothing that waits in between."""
        t2_ns = time.time_ns()
        try:
            request = CLOCK_REQUEST_DECODER.decode(payload)
        except DECODE_ERRORS:
            with self._lock:
                self.bad_requests += 1  # counted only: a reply would be a wrong exchange
            return None
        with self._lock:
            self.answered += 1
        return encode(ClockReply(request.t1_ns, t2_ns, time.time_ns()))

    def close(self) -> None:
        if self._handle is not None:
            self._handle.undeclare()
            self._handle = None


@dataclass
class RobotClock:
    """One robot's latest estimate, as it reported it."""

    offset_ns: int | None = None
    delay_ns: int | None = None
    samples: int = 0
    requests: int = 0
    replies: int = 0
    #: |offset| exceeds the bound now, whatever the asymmetry (until it is certainly back)
    flagged: bool = False


class ClockWatch:
    """Robots' clock estimates: correction of the ingest's latencies, and the bound."""

    def __init__(self, config: CeddpClockConfig, ingest: Ingest, event: EventSink) -> None:
        self.config = config
        self.ingest = ingest
        self._event = event
        self.robots: dict[str, RobotClock] = {}

    @property
    def bound_ns(self) -> int:
        return round(self.config.max_offset_ms * 1e6)

    def observe(self, robot: str, clock: ClockStats | None) -> None:
        """A report's estimate (control worker, ``ingest.lock`` held)."""
        if clock is None:
            return
        entry = self.robots.setdefault(robot, RobotClock())
        entry.requests, entry.replies = clock.requests, clock.replies
        if clock.offset_ns is None or clock.delay_ns is None:
            return
        entry.offset_ns, entry.delay_ns, entry.samples = (
            clock.offset_ns,
            clock.delay_ns,
            clock.samples,
        )
        if self.config.correct:
            self.ingest.set_clock_offset(robot, clock.offset_ns)
        # the truth is within offset +/- delay / 2 (the whole asymmetry on one side): flag
        # only a robot certainly beyond the bound, lower the flag once it is certainly within
        error_ns = (clock.delay_ns + 1) // 2
        if entry.flagged:
            change = abs(clock.offset_ns) + error_ns <= self.bound_ns
        else:
            change = abs(clock.offset_ns) - error_ns > self.bound_ns
        if change:
            entry.flagged = not entry.flagged
            self._event(*self._bound_event(robot, entry))

    def _bound_event(self, robot: str, entry: RobotClock) -> tuple[str, str]:
        assert entry.offset_ns is not None and entry.delay_ns is not None
        offset = f"{entry.offset_ns / 1e6:+.1f} ms (within {entry.delay_ns / 2e6:.1f} ms)"
        bound = f"{self.config.max_offset_ms:g} ms ([clock] max_offset_ms)"
        if not entry.flagged:
            return f"robot {robot}: clock offset {offset} is back within {bound}", "INFO"
        corrected = (
            "its latencies are corrected by the offset meanwhile"
            if self.config.correct
            else "its latencies are NOT corrected ([clock] correct = false)"
        )
        return (
            f"robot {robot}: clock offset {offset} to the CEDDP exceeds {bound}: set up NTP or "
            f"chrony on it; {corrected}",
            "WARN",
        )

    def fleet_summary(self) -> dict[str, Any]:
        """The summary's top-level ``clock`` section."""
        return {
            "corrected": self.config.correct,
            "max_offset_ms": self.config.max_offset_ms,
            "flagged": self.flagged(),
        }

    def flagged(self) -> list[str]:
        return sorted(robot for robot, entry in self.robots.items() if entry.flagged)

    def corrected(self, robot: str) -> bool:
        """Whether the robot's latencies are measured on this CEDDP's clock now."""
        entry = self.robots.get(robot)
        return self.config.correct and entry is not None and entry.offset_ns is not None

    def frame_row(self, robot: str) -> dict[str, float]:
        """The robot's clock in a metrics frame (``clock_offset_ms``, ``clock_delay_ms``; none
        before its first estimate)."""
        entry = self.robots.get(robot)
        if entry is None or entry.offset_ns is None or entry.delay_ns is None:
            return {}
        return {
            "clock_offset_ms": entry.offset_ns / 1e6,
            "clock_delay_ms": entry.delay_ns / 1e6,
            "clock_over_bound": float(entry.flagged),
        }

    def summary(self, robot: str) -> dict[str, Any]:
        """The robot's ``clock`` section of the summary (call with ``ingest.lock`` held);
        ``uncorrected_samples``: those measured on the robot's own clock (before its first
        estimate, or all of them when correction is off)."""
        entry = self.robots.get(robot, RobotClock())
        uncorrected = (
            self.ingest.clock_uncorrected(robot)
            if self.config.correct
            else sum(m.received for (r, _), m in self.ingest.topics.items() if r == robot)
        )
        return {
            "offset_ms": None if entry.offset_ns is None else round(entry.offset_ns / 1e6, 3),
            "delay_ms": None if entry.delay_ns is None else round(entry.delay_ns / 1e6, 3),
            "samples": entry.samples,
            "requests": entry.requests,
            "replies": entry.replies,
            "max_offset_ms": self.config.max_offset_ms,
            "over_bound": entry.flagged,
            "corrected": self.corrected(robot),
            "uncorrected_samples": uncorrected,
        }
