"""The robot's clock exchanges against the CEDDP's clock service, on the in-memory bus."""

from __future__ import annotations

import threading
import time

from arpz.ceddp.clock_service import ClockService
from arpz.core.config import RobotClockConfig
from arpz.core.transport import ReplyCallback
from arpz.robot.clock_sync import ClockSync
from arpz.transport.memory import MemoryBus, MemoryTransport
from tests.support import wait_until


def test_a_shifted_robot_measures_its_shift_against_the_ceddp() -> None:
    bus = MemoryBus()
    service = ClockService(MemoryTransport(bus), "f")
    service.start()
    sync = ClockSync(RobotClockConfig(shift_s=0.25, burst=3), MemoryTransport(bus), "f")
    assert sync.first_estimate(1.0)
    stats = sync.stats()
    assert stats.offset_ns is not None and stats.delay_ns is not None
    # the CEDDP's clock minus the robot's: -shift, within the in-process round trip
    assert abs(stats.offset_ns + 250_000_000) <= stats.delay_ns / 2 + 1_000_000
    assert (stats.requests, stats.replies, stats.samples) == (3, 3, 3)
    assert service.answered == 3
    sync.exchange()
    assert sync.stats().samples == 6


def test_without_a_clock_service_there_is_no_estimate_and_it_says_so() -> None:
    sync = ClockSync(RobotClockConfig(burst=2), MemoryTransport(MemoryBus()), "f")
    assert not sync.first_estimate(0.01)
    stats = sync.stats()
    assert stats.offset_ns is None and (stats.requests, stats.replies) == (2, 0)


def test_bad_requests_and_bad_replies_are_counted_not_used() -> None:
    bus = MemoryBus()
    server = MemoryTransport(bus)
    service = ClockService(server, "f")
    assert service.answer(b"\xc1") is None and service.bad_requests == 1
    server.serve("arpz/f/ceddp/clock", lambda payload: b"not msgpack \xc1")
    sync = ClockSync(RobotClockConfig(burst=1), MemoryTransport(bus), "f")
    sync.exchange()
    assert sync.bad_replies == 1 and sync.stats().offset_ns is None


def test_the_wall_clock_of_a_robot_is_shifted_by_shift_s() -> None:
    sync = ClockSync(RobotClockConfig(shift_s=-2.0), MemoryTransport(MemoryBus()), "f")
    assert abs(sync.wall_ns() - (time.time_ns() - 2_000_000_000)) < 50_000_000


class _SlowReplies(MemoryTransport):
    """Replies come back ``reply_delay_s`` late (a congested link back to the robot): an
    exchange whose delay is all on one side, so its offset is off by half of it."""

    def __init__(self, bus: MemoryBus) -> None:
        super().__init__(bus)
        self.reply_delay_s = 0.0

    def request(
        self, key: str, payload: bytes, on_reply: ReplyCallback, *, timeout_s: float
    ) -> None:
        delay_s = self.reply_delay_s

        def later(answer: bytes) -> None:
            if delay_s:
                threading.Timer(delay_s, on_reply, args=(answer,)).start()
            else:
                on_reply(answer)

        super().request(key, payload, later, timeout_s=timeout_s)


def test_settling_in_calm_replaces_a_first_estimate_taken_in_congestion() -> None:
    """The load generator's case: the first burst's replies come 40 ms late (the estimate is
    off by about 20 ms, though both clocks are one); a settling burst on a calm link waits for
    all of its replies, and the estimate is then within one or two milliseconds."""
    bus = MemoryBus()
    ClockService(MemoryTransport(bus), "f").start()
    link = _SlowReplies(bus)
    sync = ClockSync(RobotClockConfig(burst=3), link, "f")
    link.reply_delay_s = 0.04
    assert sync.first_estimate(1.0)
    off = sync.stats().offset_ns
    assert off is not None and off <= -15_000_000, off  # the congested estimate
    wait_until(lambda: sync.replies == 3, what="the congested burst's last replies")
    link.reply_delay_s = 0.002  # calm: replies still come after settle's requests returned
    assert sync.settle(1.0)
    stats = sync.stats()
    assert stats.offset_ns is not None and abs(stats.offset_ns) < 2_000_000, stats
    # the accepted exchanges of the window: the calm burst's, and those of the congested one
    # within the margin of its fastest (timers' jitter decides how many)
    assert 1 <= stats.samples <= 6, stats


def test_settling_without_a_clock_service_gives_up_in_time() -> None:
    sync = ClockSync(RobotClockConfig(burst=2), MemoryTransport(MemoryBus()), "f")
    started = time.monotonic()
    assert not sync.settle(0.05)
    assert time.monotonic() - started < 1.0


def test_replies_queued_for_good_never_become_the_estimate() -> None:
    """Issue 39 on the in-memory bus: after a calm start every reply comes 60 ms late (a
    saturated link back to the robot: its exchanges say about -30 ms, though both clocks are
    one). Many windows of them later the estimate is still the calm one, and they are
    counted as rejected, not as bad replies."""
    bus = MemoryBus()
    ClockService(MemoryTransport(bus), "f").start()
    link = _SlowReplies(bus)
    sync = ClockSync(RobotClockConfig(burst=4, window=4), link, "f")
    assert sync.first_estimate(1.0)
    wait_until(lambda: sync.replies == 4, what="the calm burst's replies")
    calm = sync.stats()
    assert calm.offset_ns is not None and abs(calm.offset_ns) < 2_000_000, calm
    assert calm.samples == 4
    link.reply_delay_s = 0.06
    for _ in range(3):
        sync.exchange()
    wait_until(lambda: sync.replies == 16, what="the slow bursts' replies")
    stats = sync.stats()
    # the last calm exchange of the window when it slid past the others (held since)
    assert stats.offset_ns is not None and abs(stats.offset_ns) < 2_000_000, stats
    assert stats.delay_ns is not None and stats.delay_ns < 4_000_000, stats
    assert sync.rejected == 12 and sync.bad_replies == 0
