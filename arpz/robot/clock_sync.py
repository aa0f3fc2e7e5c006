"""The robot's clock against the CEDDP's: NTP-style exchanges over Zenoh, kept up to date.

Every ``[clock] period_s`` the scheduler runs ``ClockSync.exchange``: a burst of requests on
``ceddp/clock``, each stamped t1 on the robot's clock; the CEDDP's reply carries t2 and t3 on
its own, and the reply's arrival is t4 (arpz/core/protocol/clock.py has the arithmetic). The
estimate is the fastest exchange of the last ``window`` among those whose delay was near the least
seen
since start (``MinDelayFilter``: a queued or retransmitted exchange never becomes the estimate;
the previous one is held meanwhile); it travels in every ``RobotStats`` and ``Announce``
(``clock``), and the CEDDP corrects this robot's latencies by it. The floor's slow rise is timed
on the monotonic clock, so that a step of the wall clock does not move it.

Replies arrive on a Zenoh thread: ``_on_reply`` stamps t4 first and only records, under a lock.

``[clock] shift_s`` adds a fixed amount to every stamp this robot makes (``wall_ns``): a test
and diagnostic aid that makes a robot whose clock is off on purpose, on one host.
"""

from __future__ import annotations

import logging
import threading
import time

from arpz.core import keys
from arpz.core.config import RobotClockConfig
from arpz.core.errors import ArpzError
from arpz.core.messages import (
    CLOCK_REPLY_DECODER,
    DECODE_ERRORS,
    ClockRequest,
    ClockStats,
    encode,
)
from arpz.core.protocol.clock import Exchange, MinDelayFilter
from arpz.core.throttled_log import ThrottledLog
from arpz.core.transport import Transport

log = logging.getLogger(__name__)
throttled = ThrottledLog(log)


class ClockSync:
    """The exchanges (scheduler thread), their replies (Zenoh's thread), the estimate (any)."""

    def __init__(self, config: RobotClockConfig, transport: Transport, fleet: str) -> None:
        self.config = config
        self._transport = transport
        self._key = keys.ceddp_clock_key(fleet)
        self._shift_ns = round(config.shift_s * 1e9)
        self._filter = MinDelayFilter(config.window)
        self._lock = threading.Lock()
        self._first = threading.Event()
        self.requests = 0
        self.replies = 0
        #: replies that could not be decoded, or could not be from this robot's requests
        self.bad_replies = 0
        #: requests the transport refused to send (session closing)
        self.send_failures = 0
        #: ``settle``'s burst: its first request's stamp, and its replies so far
        self._settle_from_ns = 2**63
        self._settle_replies = 0
        self._settled = threading.Event()

    def wall_ns(self) -> int:
        """This robot's wall clock for every stamp it makes (shifted by ``shift_s``)."""
        return time.time_ns() + self._shift_ns

    def exchange(self, _now_s: float = 0.0) -> None:
        """A scheduler job: send a burst of requests; the replies come back on their own."""
        for _ in range(self.config.burst):
            t1_ns = self.wall_ns()
            with self._lock:
                self.requests += 1
            try:
                self._transport.request(
                    self._key,
                    encode(ClockRequest(t1_ns)),
                    self._on_reply,
                    timeout_s=self.config.timeout_s,
                )
            except ArpzError as exc:
                with self._lock:
                    self.send_failures += 1
                throttled.warning("clock request", "clock request not sent: %s", exc)
                return

    def first_estimate(self, timeout_s: float) -> bool:
        """A burst, then wait (bounded) for its first reply: at start, so that the announcement
        carries an estimate before the first reading goes out."""
        self.exchange()
        return self._first.wait(timeout_s)

    def settle(self, timeout_s: float) -> bool:
        """A burst, and wait (bounded) until every one of its replies came: whether they did.
        For a caller that knows the link is calm now (``RobotAgent.settle_clock``): the
        estimate is then the fastest of this burst's exchanges and the earlier ones of the
        filter's window, when they are near the least delay seen (a calm link's are)."""
        with self._lock:
            self._settle_from_ns = self.wall_ns()
            self._settle_replies = 0
            self._settled.clear()
        self.exchange()
        return self._settled.wait(timeout_s)

    def _on_reply(self, payload: bytes) -> None:
        t4_ns = self.wall_ns()
        try:
            reply = CLOCK_REPLY_DECODER.decode(payload)
        except DECODE_ERRORS as exc:
            with self._lock:
                self.bad_replies += 1
            throttled.warning("clock reply", "undecodable clock reply: %s", exc)
            return
        now_ns = time.monotonic_ns()
        exchange = Exchange(reply.t1_ns, reply.t2_ns, reply.t3_ns, t4_ns)
        with self._lock:
            self.replies += 1
            if not self._filter.add(exchange, now_ns):
                self.bad_replies += 1
                return
            if reply.t1_ns >= self._settle_from_ns:
                self._settle_replies += 1
                if self._settle_replies >= self.config.burst:
                    self._settled.set()
        self._first.set()

    @property
    def rejected(self) -> int:
        """Plausible replies whose delay was too far above the least seen to be used."""
        with self._lock:
            return self._filter.rejected

    def stats(self) -> ClockStats:
        """The estimate now, for the robot's reports."""
        with self._lock:
            estimate = self._filter.estimate()
            requests, replies = self.requests, self.replies
        if estimate is None:
            return ClockStats(requests=requests, replies=replies)
        return ClockStats(
            offset_ns=estimate.offset_ns,
            delay_ns=estimate.delay_ns,
            samples=estimate.samples,
            stamp_ns=estimate.stamp_ns,
            requests=requests,
            replies=replies,
        )
