"""The Hello bookkeeping at the origin (seed 001 Fig. 9): a Hello is a round trip only if it comes
back within the timeout, whether or not a sweep declared it lost first."""

from __future__ import annotations

from arpz.robot.hello import HelloTracker

S = 1_000_000_000


def test_a_hello_back_within_the_timeout_is_a_round_trip() -> None:
    tracker = HelloTracker(timeout_s=2.0)
    tracker.on_sent(1, t0_ns=0)
    assert tracker.on_returned(1, now_ns=S // 2) == 500.0
    stats = tracker.stats()
    assert (stats.sent, stats.received, stats.lost, stats.late) == (1, 1, 0, 0)


def test_a_hello_back_after_the_timeout_is_lost_even_before_a_sweep() -> None:
    # the shutdown drain waits for Hellos in flight without sweeping: one that comes back 2.5 s
    # after it left was counted as a 2.5 s round trip before
    tracker = HelloTracker(timeout_s=2.0)
    tracker.on_sent(1, t0_ns=0)
    assert tracker.on_returned(1, now_ns=5 * S // 2) is None
    stats = tracker.stats()
    assert (stats.sent, stats.received, stats.lost, stats.late, stats.outstanding) == (
        1,
        0,
        1,
        1,
        0,
    )
    assert stats.rtt_ms_max is None or stats.rtt_ms_max < 2000


def test_a_hello_swept_as_lost_and_back_later_is_late_not_lost_twice() -> None:
    tracker = HelloTracker(timeout_s=2.0)
    tracker.on_sent(1, t0_ns=0)
    assert tracker.expire(now_ns=3 * S) == 1
    assert tracker.on_returned(1, now_ns=4 * S) is None
    stats = tracker.stats()
    assert (stats.sent, stats.received, stats.lost, stats.late) == (1, 0, 1, 1)
