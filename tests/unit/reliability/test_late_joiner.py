"""A reader that (re)joins a KEEP_ALL TRANSIENT_LOCAL writer with a long history while the writer
keeps writing fast: what a restarted CEDDP does (issue 15, item 4). Nothing the writer still
holds is declared lost, and the history is resent about once, not once per NACK."""

from __future__ import annotations

import random

from arpz.core.protocol import wire
from arpz.core.protocol._common import new_guid
from arpz.core.protocol.actions import Send
from arpz.core.protocol.qos import DurabilityPolicy, HistoryPolicy, QosProfile
from arpz.core.protocol.reader_machine import QUEUED_HOLD_FACTOR, ReaderMachine
from arpz.core.protocol.timers import FakeClock
from arpz.core.protocol.writer_machine import WriterMachine
from tests.unit.reliability.lossy_bus import Link, LossyBus

DURABLE = QosProfile(
    history=HistoryPolicy.KEEP_ALL,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
    max_samples=5000,
)


def run(link: Link, backlog: int, seed: int = 1) -> tuple[ReaderMachine, WriterMachine]:
    clock = FakeClock()
    bus = LossyBus(random.Random(seed), link, clock)
    writer = bus.add(WriterMachine("robot/r1/imu", DURABLE, new_guid(), clock))
    w = writer.machine
    assert isinstance(w, WriterMachine)
    for i in range(backlog):  # written while no reader was there (the CEDDP was down)
        bus.write(writer, b"%d" % i)
    reader = bus.add(ReaderMachine("robot/*/imu", DURABLE, new_guid(), clock))
    for i in range(2000):  # and it keeps writing at 2 kHz while the reader catches up
        bus.write(writer, b"%d" % (backlog + i))
        bus.run_for(0.0005, dt_s=0.0005)
    bus.run_for(3.0)
    r = reader.machine
    assert isinstance(r, ReaderMachine)
    return r, w


def test_a_late_reader_gets_the_whole_history_without_false_loss_or_repeated_resends() -> None:
    r, w = run(Link(delay_s=0.002, jitter_s=0.004), backlog=3000)
    assert r.lost == 0 and r.delivered == 5000, (r.lost, r.delivered)
    # the backlog goes out once by resend (``-s`` prints it; 8 329 before, 2.8 times)
    print(f"4-10 ms round trip: {w.retransmitted} resends of 3 000")
    assert w.retransmitted <= 1.1 * 3000, (w.retransmitted, w.resends_held_off)


def test_on_a_lossy_link_too() -> None:
    r, w = run(Link(loss=0.05, delay_s=0.002, jitter_s=0.004), backlog=3000, seed=3)
    assert r.lost == 0 and r.delivered == 5000, (r.lost, r.delivered)
    assert w.retransmitted <= 1.5 * 3000, (w.retransmitted, w.resends_held_off)


def test_a_catch_up_longer_than_the_reorder_timeout_declares_nothing_lost() -> None:
    """50 ms each way: 3 000 samples at 256 resends per NACK take about 1.2 s of round trips,
    more than reorder_timeout_s (0.5 s); what the writer still holds is waited for."""
    r, w = run(Link(delay_s=0.05, jitter_s=0.002), backlog=3000, seed=5)
    assert r.lost == 0 and r.delivered == 5000, (r.lost, r.delivered)  # before: 1 921 lost
    # Over a 100 ms round trip the reader's ACKNACKs (one per ack request of the live data) used
    # to ask again for resends still in flight: timed from the latest NACK sent, the round trip
    # measured 2.5 ms, and the history went out 6.6 times (19 714 resends). Timed by the echo of
    # the NACK each resend answers, it goes out about 1.15 times (``-s`` prints it: before the
    # first answer, the reader's hold of nack_period_s and the writer's first holdoff of 50 ms
    # are shorter than this round trip, and the first 256 go out twice more).
    print(f"100 ms round trip: {w.retransmitted} resends of 3 000, {w.resends_held_off} held off")
    assert w.retransmitted <= 1.2 * 3000, (w.retransmitted, w.resends_held_off)


def test_the_nack_round_trip_is_timed_by_the_resends_that_echo_it() -> None:
    """The resends echo the count of the ACKNACK they answer: over a 100 ms round trip with NACKs
    going out all the time (one per ack request of the live data), the measured answer time is
    the round trip (plus the time to take the answers in), not the gap to the latest NACK."""
    r, _ = run(Link(delay_s=0.05), backlog=3000, seed=7)
    (proxy,) = r.writers.values()
    assert 0.1 <= proxy.srtt_s < 0.15, proxy.srtt_s  # timed from the latest NACK: 2.5 ms


def _reasks(backlog: bool) -> list[float]:
    """When a reader asks again for the history its first NACK asked for, if no answer ever
    comes (the link goes dead right after that NACK): the times after the first NACK."""
    clock = FakeClock()
    bus = LossyBus(random.Random(1), Link(delay_s=0.002), clock)
    writer = bus.add(WriterMachine("robot/r1/imu", DURABLE, new_guid(), clock))
    for i in range(600):
        bus.write(writer, b"%d" % i)
    reader = bus.add(ReaderMachine("robot/*/imu", DURABLE, new_guid(), clock))
    r = reader.machine
    assert isinstance(r, ReaderMachine)
    if backlog:  # as if the channel reported samples queued before the machine at every tick
        r.tick = lambda backlog=0: ReaderMachine.tick(r, 1)  # type: ignore[method-assign]
    asked: list[tuple[float, int]] = []
    original = bus.send

    def spy(msg: Send) -> None:
        an = wire.decode_acknack(msg.payload) if msg.attachment is None else None
        if an is not None and an.missing:
            asked.append((clock.monotonic_s(), an.missing[0][0]))
            bus.link.loss = 1.0  # nothing gets through any more
        original(msg)

    bus.send = spy  # type: ignore[method-assign]
    bus.run_for(1.0)
    t0 = asked[0][0]
    return [t - t0 for t, lo in asked[1:] if lo == 1]


def test_a_reader_with_samples_queued_before_it_asks_again_later_but_still_asks() -> None:
    """Samples queued before the reader (a full pull) may hold the resends it asked for: it
    waits QUEUED_HOLD_FACTOR times longer before asking again, but it does ask again, so a lost
    NACK or resend is recovered under a lasting backlog too."""
    plain, queued = _reasks(backlog=False), _reasks(backlog=True)
    assert plain and queued, (plain, queued)
    assert queued[0] >= QUEUED_HOLD_FACTOR * plain[0] * 0.9, (plain, queued)
    assert len(queued) < len(plain), (plain, queued)
