"""The NTP exchange's arithmetic and the minimum-delay filter (arpz.protocol.clock)."""

from __future__ import annotations

import msgspec
import pytest
from hypothesis import given
from hypothesis import strategies as st

from arpz.messages import STATS_DECODER, ClockStats, RobotStats, encode
from arpz.protocol.clock import Exchange, MinDelayFilter

#: nanoseconds: offsets up to an hour either way, one-way delays up to 10 s, holds up to 1 s
offsets = st.integers(min_value=-3_600 * 10**9, max_value=3_600 * 10**9)
delays = st.integers(min_value=0, max_value=10 * 10**9)
holds = st.integers(min_value=0, max_value=10**9)
starts = st.integers(min_value=10**18, max_value=2 * 10**18)


def exchange(t1: int, offset: int, up: int, hold: int, down: int) -> Exchange:
    """A robot at t1 (its clock); the CEDDP's clock is the robot's + offset."""
    t2 = t1 + up + offset
    t3 = t2 + hold
    t4 = t3 - offset + down
    return Exchange(t1, t2, t3, t4)


@given(t1=starts, offset=offsets, one_way=delays, hold=holds)
def test_symmetric_delays_give_the_exact_offset(
    t1: int, offset: int, one_way: int, hold: int
) -> None:
    e = exchange(t1, offset, one_way, hold, one_way)
    assert e.offset_ns == offset
    assert e.delay_ns == 2 * one_way
    assert e.plausible


@given(t1=starts, offset=offsets, up=delays, down=delays, hold=holds)
def test_asymmetric_delays_err_by_at_most_half_the_delay(
    t1: int, offset: int, up: int, down: int, hold: int
) -> None:
    e = exchange(t1, offset, up, hold, down)
    assert e.delay_ns == up + down
    # the error is (up - down) / 2, rounded down: never beyond delay / 2, plus the rounding
    assert abs(e.offset_ns - offset) <= e.delay_ns / 2 + 1


@given(
    t1=starts,
    offset=offsets,
    trips=st.lists(st.tuples(delays, delays, holds), min_size=1, max_size=30),
    window=st.integers(min_value=1, max_value=16),
)
def test_the_filter_keeps_the_fastest_of_the_last_window(
    t1: int, offset: int, trips: list[tuple[int, int, int]], window: int
) -> None:
    f = MinDelayFilter(window)
    made = []
    for i, (up, down, hold) in enumerate(trips):
        e = exchange(t1 + i * 10**9, offset, up, hold, down)
        made.append(e)
        assert f.add(e)
    estimate = f.estimate()
    assert estimate is not None
    recent = made[-window:]
    fastest = min(e.delay_ns for e in recent)
    assert estimate.delay_ns == fastest
    assert estimate.samples == len(recent)
    assert estimate.offset_ns in {e.offset_ns for e in recent if e.delay_ns == fastest}
    assert abs(estimate.offset_ns - offset) <= estimate.error_bound_ns + 1


def test_one_fast_exchange_among_queued_ones_wins() -> None:
    """Queues delay one direction: the queued exchanges are off by half their delay, the
    fast one is right, and the filter picks it."""
    f = MinDelayFilter(8)
    offset = -500_000_000
    for up in (40_000_000, 25_000_000, 60_000_000):
        f.add(exchange(10**18, offset, up, 1000, 200_000))
    f.add(exchange(10**18 + 5, offset, 150_000, 1000, 150_000))
    estimate = f.estimate()
    assert estimate is not None and estimate.offset_ns == offset
    assert estimate.delay_ns == 300_000


def test_implausible_exchanges_are_counted_and_never_kept() -> None:
    f = MinDelayFilter(4)
    assert f.estimate() is None
    assert not f.add(Exchange(t1_ns=100, t2_ns=50, t3_ns=40, t4_ns=200))  # replied before receipt
    assert not f.add(Exchange(t1_ns=100, t2_ns=50, t3_ns=60, t4_ns=90))  # reply before request
    assert not f.add(Exchange(t1_ns=100, t2_ns=50, t3_ns=200, t4_ns=120))  # held > the wait
    assert f.refused == 3
    assert f.estimate() is None


def test_a_window_below_one_is_refused() -> None:
    with pytest.raises(ValueError, match="window"):
        MinDelayFilter(0)


def test_robot_stats_without_a_clock_still_decode() -> None:
    """An older robot's report (no clock, no versions) decodes with the defaults, and a new
    one round-trips its clock."""

    class OldRobotStats(msgspec.Struct, frozen=True):
        robot: str
        incarnation: str
        stamp_ns: int
        final: bool
        topics: dict[str, int]

    old = STATS_DECODER.decode(msgspec.msgpack.encode(OldRobotStats("r1", "a", 1, False, {})))
    assert old.clock is None and old.arpz_version == ""
    clock = ClockStats(offset_ns=-5, delay_ns=10, samples=3, stamp_ns=7, requests=4, replies=3)
    new = RobotStats("r1", "a", 1, False, {}, clock=clock, arpz_version="0.1")
    assert STATS_DECODER.decode(encode(new)).clock == clock
