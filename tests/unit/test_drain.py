"""``arpz.channel.io.drain``: a stopping robot waits for its unacknowledged samples while the
CEDDP keeps acknowledging them, and not after it stops (a fake clock: no real waiting)."""

from __future__ import annotations

from arpz.channel.io import drain


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


class SlowReader:
    """An outlet whose readers acknowledge ``per_poll`` more seqs each time it is polled, up to
    ``written``, until ``stops_at`` (a CEDDP that dies or stalls); every poll takes its timeout."""

    def __init__(self, clock: Clock, written: int, per_poll: int, stops_at: float = 1e9) -> None:
        self.clock, self.written, self.per_poll, self.stops_at = clock, written, per_poll, stops_at
        self.acked = 0

    def wait_for_acknowledgments(self, timeout_s: float) -> bool:
        self.clock.now += timeout_s
        if self.clock.now < self.stops_at:
            self.acked = min(self.written, self.acked + self.per_poll)
        return self.acked >= self.written

    def acknowledged_through(self) -> int | None:
        return self.acked


def test_a_draining_ceddp_is_waited_for_past_the_stall_bound() -> None:
    clock = Clock()
    # 10 s worth of polls at 0.05 s each: far beyond the 2 s stall bound, progressing throughout
    outlets = [SlowReader(clock, written=200, per_poll=1), SlowReader(clock, written=3, per_poll=1)]
    assert drain(outlets, stall_s=2.0, limit_s=30.0, clock=clock)
    assert all(o.acked == o.written for o in outlets)
    assert 9.0 < clock.now < 11.0


def test_no_progress_for_the_stall_bound_gives_up() -> None:
    clock = Clock()
    outlet = SlowReader(clock, written=1000, per_poll=1, stops_at=3.0)
    assert not drain([outlet], stall_s=2.0, limit_s=30.0, clock=clock)
    assert 0 < outlet.acked < 1000
    assert 4.9 <= clock.now <= 5.2  # the last progress at 3 s, then 2 s of nothing


def test_the_limit_holds_even_while_progressing() -> None:
    clock = Clock()
    outlet = SlowReader(clock, written=10_000, per_poll=1)
    assert not drain([outlet], stall_s=2.0, limit_s=5.0, clock=clock)
    assert 5.0 <= clock.now <= 5.1


def test_nothing_unacknowledged_returns_at_once_and_a_plain_outlet_counts_as_done() -> None:
    clock = Clock()
    done = SlowReader(clock, written=0, per_poll=1)

    class Plain:
        def wait_for_acknowledgments(self, timeout_s: float) -> bool:
            return True

        def acknowledged_through(self) -> int | None:
            return None

    assert drain([done, Plain()], stall_s=2.0, limit_s=30.0, clock=clock)
    assert clock.now <= 0.05
    assert drain([], stall_s=2.0, limit_s=30.0, clock=clock)
