"""Properties of the writer and reader state machines over a lossy, duplicating, reordering bus."""

from __future__ import annotations

import random
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from arpz.core.protocol import wire
from arpz.core.protocol._common import new_guid
from arpz.core.protocol.actions import Send
from arpz.core.protocol.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    LivelinessPolicy,
    QosProfile,
    ReliabilityPolicy,
)
from arpz.core.protocol.reader_machine import ReaderMachine
from arpz.core.protocol.timers import FakeClock
from arpz.core.protocol.writer_machine import LOSSY_HOLD_PERIODS, QUIET_HEARTBEAT_S, WriterMachine
from tests.unit.reliability.lossy_bus import Link, LossyBus, Node, publish

FAST = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])

links = st.builds(
    Link,
    loss=st.sampled_from([0.0, 0.1, 0.3, 0.5]),
    duplicate=st.sampled_from([0.0, 0.1]),
    delay_s=st.sampled_from([0.0005, 0.002]),
    jitter_s=st.sampled_from([0.0, 0.004]),
)


def world(seed: int, link: Link) -> tuple[LossyBus, FakeClock]:
    clock = FakeClock()
    return LossyBus(random.Random(seed), link, clock), clock


def check_invariant(reader: Node, writer: Node) -> list[int]:
    r, w = reader.machine, writer.machine
    assert isinstance(r, ReaderMachine) and isinstance(w, WriterMachine)
    seqs = [info.seq for _, info in reader.delivered if info.writer == w.hex]
    assert seqs == sorted(set(seqs)), "delivered out of order or twice"
    start = r.match_start(w.hex)
    assert start is not None, "never synced"
    proxy = r.writers[(w.topic, w.guid)]
    assert proxy.delivered + proxy.lost == w.last_seq - start + 1
    assert all(s >= start for s in seqs)
    for payload, info in reader.delivered:
        if info.writer == w.hex:
            assert payload == b"%d" % (info.seq - 1)
    return seqs


qos_choices = st.sampled_from(
    [
        QosProfile(history=HistoryPolicy.KEEP_ALL, max_samples=40),
        QosProfile(depth=1),
        QosProfile(depth=5, reorder_timeout_s=0.05),
        QosProfile(reliability=ReliabilityPolicy.BEST_EFFORT, depth=5),
        QosProfile(durability=DurabilityPolicy.TRANSIENT_LOCAL, depth=20),
        QosProfile(depth=5, batch_max_samples=8, batch_max_delay_s=0.003),
        QosProfile(history=HistoryPolicy.KEEP_ALL, max_samples=40, batch_max_samples=16),
    ]
)


@FAST
@given(
    seed=st.integers(0, 2**32),
    link=links,
    qos=qos_choices,
    n=st.integers(1, 150),
    period_s=st.sampled_from([0.0, 0.001, 0.004]),
)
def test_delivered_plus_lost_equals_sent_without_duplicates(
    seed: int, link: Link, qos: QosProfile, n: int, period_s: float
) -> None:
    bus, _ = world(seed, link)
    writer = bus.add(WriterMachine("t/a", qos, new_guid(), bus.clock))
    reader = bus.add(ReaderMachine("t/*", qos, new_guid(), bus.clock))
    bus.run_for(0.3)
    publish(bus, writer, n, period_s)
    bus.run_for(2.0)
    check_invariant(reader, writer)
    r = reader.machine
    assert isinstance(r, ReaderMachine)
    lost_events = sum(s.total_count_change for e, s in reader.events if e == "message_lost")  # type: ignore[attr-defined]
    assert lost_events == r.lost


@FAST
@given(
    seed=st.integers(0, 2**32),
    link=links,
    n=st.integers(1, 200),
    batch=st.sampled_from([1, 4, 32]),
)
def test_keep_all_delivers_everything_in_order(seed: int, link: Link, n: int, batch: int) -> None:
    qos = QosProfile(
        history=HistoryPolicy.KEEP_ALL,
        max_samples=30,
        reorder_timeout_s=60.0,
        batch_max_samples=batch,
    )
    bus, _ = world(seed, link)
    writer = bus.add(WriterMachine("t/a", qos, new_guid(), bus.clock))
    reader = bus.add(ReaderMachine("t/a", qos, new_guid(), bus.clock))
    bus.run_for(0.3)
    publish(bus, writer, n, 0.0)
    bus.run_for(3.0)
    seqs = check_invariant(reader, writer)
    assert seqs == list(range(1, n + 1))
    assert reader.machine.lost == 0


@FAST
@given(seed=st.integers(0, 2**32), link=links, n_writers=st.integers(2, 4), n=st.integers(1, 60))
def test_many_writers_to_one_wildcard_reader(seed: int, link: Link, n_writers: int, n: int) -> None:
    qos = QosProfile(history=HistoryPolicy.KEEP_ALL, max_samples=30, reorder_timeout_s=60.0)
    bus, _ = world(seed, link)
    writers = [
        bus.add(WriterMachine(f"f/robot/r{i}/sensor/s", qos, new_guid(), bus.clock))
        for i in range(n_writers)
    ]
    reader = bus.add(ReaderMachine("f/robot/*/sensor/*", qos, new_guid(), bus.clock))
    bus.run_for(0.3)
    for i in range(n):
        for w in writers:
            while not w.machine.has_room():  # type: ignore[union-attr]
                bus.step()
            bus.write(w, b"%d" % i)
        bus.step()
    bus.run_for(3.0)
    for w in writers:
        assert check_invariant(reader, w) == list(range(1, n + 1))
    keys = {info.key for _, info in reader.delivered}
    assert keys == {f"f/robot/r{i}/sensor/s" for i in range(n_writers)}


@FAST
@given(seed=st.integers(0, 2**32), link=links, n_readers=st.integers(2, 3), n=st.integers(1, 80))
def test_one_writer_to_many_readers(seed: int, link: Link, n_readers: int, n: int) -> None:
    qos = QosProfile(history=HistoryPolicy.KEEP_ALL, max_samples=25, reorder_timeout_s=60.0)
    bus, _ = world(seed, link)
    writer = bus.add(WriterMachine("t/a", qos, new_guid(), bus.clock))
    readers = [bus.add(ReaderMachine("t/a", qos, new_guid(), bus.clock)) for _ in range(n_readers)]
    bus.run_for(0.3)
    publish(bus, writer, n, 0.001)
    bus.run_for(3.0)
    for reader in readers:
        assert check_invariant(reader, writer) == list(range(1, n + 1))


def test_keep_last_depth_1_at_high_rate_loses_and_reports_every_loss() -> None:
    qos = QosProfile(depth=1)
    bus, _ = world(7, Link(loss=0.2, delay_s=0.003))
    writer = bus.add(WriterMachine("t/a", qos, new_guid(), bus.clock))
    reader = bus.add(ReaderMachine("t/a", qos, new_guid(), bus.clock))
    bus.run_for(0.3)
    for i in range(2000):
        bus.write(writer, b"%d" % i)
        if i % 4 == 0:
            bus.step(0.0005)
    bus.run_for(2.0)
    check_invariant(reader, writer)
    r, w = reader.machine, writer.machine
    assert isinstance(r, ReaderMachine) and isinstance(w, WriterMachine)
    assert r.lost > 100
    # GAPs the writer sent are confirmed losses, never more than the reader counted; whether any
    # is sent depends on the loss pattern (a NACK must reach the writer for an overwritten seq)
    assert w.lost <= r.lost
    assert w.overwritten_unacked >= w.lost


def test_transient_local_late_joiner_gets_the_history() -> None:
    qos = QosProfile(depth=5, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    bus, _ = world(3, Link(loss=0.2))
    writer = bus.add(WriterMachine("t/a", qos, new_guid(), bus.clock))
    publish(bus, writer, 12, 0.001)
    late = bus.add(ReaderMachine("t/a", qos, new_guid(), bus.clock))
    volatile = bus.add(ReaderMachine("t/a", QosProfile(depth=5), new_guid(), bus.clock))
    bus.run_for(1.0)
    assert [i.seq for _, i in late.delivered] == [8, 9, 10, 11, 12]
    assert volatile.delivered == []
    publish(bus, writer, 3, 0.001)
    bus.run_for(1.0)
    assert [i.seq for _, i in late.delivered][-3:] == [13, 14, 15]
    assert [i.seq for _, i in volatile.delivered] == [13, 14, 15]


def test_a_late_reader_asks_again_for_samples_it_had_to_ignore_before_its_sync() -> None:
    """A batch written before a TRANSIENT_LOCAL reader existed reaches it late (the writer's
    worker was slow to flush), after it knows the writer but before the SYNC: more samples than
    its pre-SYNC buffer holds. The ones it ignored are NACKed after the SYNC, not missed."""
    qos = QosProfile(depth=5, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    bus, _ = world(4, Link())
    writer = bus.add(WriterMachine("t/a", qos, new_guid(), bus.clock))
    held: list[Send] = []
    send = bus.send
    bus.send = lambda msg: held.append(msg) if msg.key == "t/a" else send(msg)  # type: ignore[method-assign]
    publish(bus, writer, 12, 0.0)  # one alone, then one batch of 11 (seqs 2-12)
    bus.run_for(0.01)
    assert len(held) == 2
    bus.send = send  # type: ignore[method-assign]
    late = bus.add(ReaderMachine("t/a", qos, new_guid(), bus.clock))
    r = late.machine
    assert isinstance(r, ReaderMachine)
    while not r.writers:
        bus.step(0.0005)
    assert not r.writers[(writer.machine.topic, writer.machine.guid)].synced
    bus.run(late, r.on_data("t/a", held[1].payload, held[1].attachment))
    assert r.stats().bad_input == 12 - 1 - 5  # beyond the pre-SYNC buffer of depth 5
    bus.run_for(1.0)
    assert [i.seq for _, i in late.delivered] == [8, 9, 10, 11, 12]
    assert r.stats().lost == 0


def test_best_effort_counts_a_batch_lost_at_the_end_of_a_stream() -> None:
    """Nothing follows a lost last batch but heartbeats: a BEST_EFFORT reader (no NACKs) counts
    it lost from their ``last``, whatever its depth (here 5, the batch 40)."""
    qos = QosProfile(reliability=ReliabilityPolicy.BEST_EFFORT, depth=5)
    bus, _ = world(2, Link())
    writer = bus.add(WriterMachine("t/a", qos, new_guid(), bus.clock))
    reader = bus.add(ReaderMachine("t/a", qos, new_guid(), bus.clock))
    bus.run_for(0.3)
    send = bus.send
    data: list[Send] = []

    def drop_all_data_but_the_first(msg: Send) -> None:
        if msg.key == "t/a":
            data.append(msg)
            if len(data) > 1:
                return
        send(msg)

    bus.send = drop_all_data_but_the_first  # type: ignore[method-assign]
    publish(bus, writer, 41, 0.0)  # one alone, then one batch of 40 (seqs 2-41), dropped
    bus.run_for(0.01)
    bus.send = send  # type: ignore[method-assign]
    bus.run_for(1.0)
    assert len(data) == 2
    assert [i.seq for _, i in reader.delivered] == [1]
    check_invariant(reader, writer)
    assert reader.machine.lost == 40


def test_a_forged_heartbeat_skips_a_best_effort_reader_one_window_at_most() -> None:
    """A heartbeat claiming more than the writer can have written since it was last heard is
    refused outright; a plausible one is trusted one window past the data, no further."""
    qos = QosProfile(reliability=ReliabilityPolicy.BEST_EFFORT, depth=5)
    bus, _ = world(3, Link())
    writer = bus.add(WriterMachine("t/a", qos, new_guid(), bus.clock))
    reader = bus.add(ReaderMachine("t/a", qos, new_guid(), bus.clock))
    bus.run_for(0.3)
    publish(bus, writer, 3, 0.001)
    bus.run_for(0.1)
    r, w = reader.machine, writer.machine
    assert isinstance(r, ReaderMachine) and isinstance(w, WriterMachine)
    impossible = wire.encode_heartbeat(0, w.guid, 1, 10**12, 999)
    bus.run(reader, r.on_heartbeat(wire.heartbeat_key("t/a", w.hex), impossible, None))
    bus.run_for(0.1)
    assert r.lost == 0 and r.implausible == 1
    forged = wire.encode_heartbeat(0, w.guid, 1, 3 + 50_000, 999)  # within 0.1 s at 1 MHz
    for _ in range(5):  # repeated: still one window past what the writer proved it sent
        bus.run(reader, r.on_heartbeat(wire.heartbeat_key("t/a", w.hex), forged, None))
        bus.run_for(0.1)
    assert r.lost == wire.MAX_BATCH
    publish(bus, writer, 3, 0.001)  # real data now arrives below the forged skip: counted late
    bus.run_for(0.1)
    assert r.lost == wire.MAX_BATCH and r.stats().late == 3


def test_incompatible_qos_does_not_match_and_both_sides_are_told() -> None:
    bus, _ = world(1, Link())
    writer = bus.add(
        WriterMachine(
            "t/a", QosProfile(reliability=ReliabilityPolicy.BEST_EFFORT), new_guid(), bus.clock
        )
    )
    reader = bus.add(ReaderMachine("t/a", QosProfile(), new_guid(), bus.clock))
    bus.run_for(0.2)
    publish(bus, writer, 5, 0.001)
    bus.run_for(0.2)
    assert reader.delivered == []
    w_events = [s for e, s in writer.events if e == "incompatible_qos"]
    r_events = [s for e, s in reader.events if e == "incompatible_qos"]
    assert len(w_events) == len(r_events) == 1
    assert w_events[0].last_policy_kind.value == "reliability"  # type: ignore[attr-defined]
    assert not [e for e, _ in writer.events + reader.events if e == "matched"]
    assert reader.machine.stats().bad_input == 0


def test_deadline_misses_are_counted_per_period_and_unchanged_keeps_the_topic_alive() -> None:
    qos = QosProfile(deadline_s=0.1)
    bus, _ = world(1, Link())
    writer = bus.add(WriterMachine("t/a", qos, new_guid(), bus.clock))
    reader = bus.add(ReaderMachine("t/a", qos, new_guid(), bus.clock))
    bus.run_for(0.05)
    publish(bus, writer, 20, 0.02)  # 0.4 s at 50 Hz: no miss
    w = writer.machine
    assert isinstance(w, WriterMachine)
    for _ in range(50):  # 1 s of held-back readings
        bus.run(writer, w.assert_unchanged())
        bus.run_for(0.02)
    assert [e for e, _ in reader.events + writer.events if e == "deadline"] == []
    bus.run_for(0.55)  # pause: 5 missed periods
    missed_r = sum(s.total_count_change for e, s in reader.events if e == "deadline")  # type: ignore[attr-defined]
    missed_w = sum(s.total_count_change for e, s in writer.events if e == "deadline")  # type: ignore[attr-defined]
    assert missed_r == 5 and missed_w == 5
    assert reader.machine.stats().unchanged >= 8


def test_liveliness_changes_when_the_writer_dies_and_when_a_manual_lease_expires() -> None:
    qos = QosProfile(
        liveliness=LivelinessPolicy.MANUAL_BY_TOPIC,
        lease_duration_s=0.2,
    )
    bus, _ = world(1, Link())
    writer = bus.add(WriterMachine("t/a", qos, new_guid(), bus.clock))
    reader = bus.add(ReaderMachine("t/a", qos, new_guid(), bus.clock))
    bus.run_for(0.05)
    publish(bus, writer, 5, 0.01)
    bus.run_for(0.5)  # no assertion for longer than the lease
    changes = [s for e, s in reader.events if e == "liveliness"]
    assert changes[-1].alive_count == 0 and changes[-1].not_alive_count == 1  # type: ignore[attr-defined]
    assert [e for e, _ in writer.events].count("liveliness") == 1
    w = writer.machine
    assert isinstance(w, WriterMachine)
    bus.run(writer, w.assert_liveliness())
    bus.run_for(0.05)
    assert [s for e, s in reader.events if e == "liveliness"][-1].alive_count == 1  # type: ignore[attr-defined]
    bus.remove(writer)
    bus.run_for(0.05)
    last = [s for e, s in reader.events if e == "liveliness"][-1]
    assert last.alive_count == 0 and last.alive_count_change == -1  # type: ignore[attr-defined]
    assert [s for e, s in reader.events if e == "matched"][-1].current_count == 0  # type: ignore[attr-defined]


def test_lifespan_expired_samples_are_dropped_and_counted() -> None:
    qos = QosProfile(lifespan_s=0.01)
    bus, _ = world(1, Link(delay_s=0.02))
    writer = bus.add(WriterMachine("t/a", qos, new_guid(), bus.clock))
    reader = bus.add(ReaderMachine("t/a", qos, new_guid(), bus.clock))
    bus.run_for(0.2)
    publish(bus, writer, 10, 0.001)
    bus.run_for(0.5)
    stats = reader.machine.stats()
    assert stats.delivered == 0 and stats.lifespan_expired == 10


def _heartbeats_while_idle(qos: QosProfile, reader_qos: QosProfile, idle_s: float) -> int:
    bus, _ = world(1, Link(delay_s=0.001))
    writer = bus.add(WriterMachine("t/a", qos, new_guid(), bus.clock))
    reader = bus.add(ReaderMachine("t/a", reader_qos, new_guid(), bus.clock))
    bus.run_for(0.3)
    publish(bus, writer, 5, 0.01)
    bus.run_for(0.5)  # acknowledged, and told so by a FINAL heartbeat
    w = writer.machine
    assert isinstance(w, WriterMachine)
    before = w.heartbeats
    bus.run_for(idle_s)
    idle = w.heartbeats - before
    publish(bus, writer, 1, 0.01)  # a write makes it speak again (its DATA asks for an ACK)
    bus.run_for(0.5)
    assert [info.seq for _, info in reader.delivered] == [1, 2, 3, 4, 5, 6]
    return idle


def test_an_idle_writer_whose_readers_have_everything_goes_quiet() -> None:
    qos = QosProfile(history=HistoryPolicy.KEEP_ALL)
    assert _heartbeats_while_idle(qos, qos, idle_s=2.0) == 0
    # a best-effort reader learns the tail only from heartbeats: they keep coming (10 a second)
    best_effort = QosProfile(reliability=ReliabilityPolicy.BEST_EFFORT)
    assert _heartbeats_while_idle(best_effort, best_effort, idle_s=2.0) >= 15
    # a liveliness lease is kept alive with a heartbeat every lease / 4
    leased = QosProfile(history=HistoryPolicy.KEEP_ALL, lease_duration_s=2.0)
    assert 3 <= _heartbeats_while_idle(leased, leased, idle_s=2.0) <= 5


def _keep_all_pair() -> tuple[LossyBus, Node, Node, WriterMachine]:
    """A KEEP_ALL writer and reader over a clean link, matched: (bus, writer, reader, its
    machine)."""
    qos = QosProfile(history=HistoryPolicy.KEEP_ALL)
    bus, _ = world(1, Link(delay_s=0.001))
    writer = bus.add(WriterMachine("t/a", qos, new_guid(), bus.clock))
    reader = bus.add(ReaderMachine("t/a", qos, new_guid(), bus.clock))
    bus.run_for(0.3)
    w = writer.machine
    assert isinstance(w, WriterMachine)
    return bus, writer, reader, w


def test_a_slow_stream_acknowledged_in_time_sends_no_heartbeats() -> None:
    """At 1 Hz each DATA asks for an ACKNACK, and the reader's answer arrives long before the
    next heartbeat period: the writer has nothing to announce, so it sends no heartbeat (it
    sent a FINAL one after every sample)."""
    bus, writer, reader, w = _keep_all_pair()
    before = w.heartbeats
    publish(bus, writer, 5, 1.0)
    assert [info.seq for _, info in reader.delivered] == [1, 2, 3, 4, 5]
    assert w.heartbeats == before


def test_a_write_whose_data_is_lost_is_heartbeated_until_it_is_acknowledged() -> None:
    bus, writer, reader, w = _keep_all_pair()
    publish(bus, writer, 2, 1.0)
    before = w.heartbeats
    send = bus.send
    bus.send = lambda msg: None if msg.key == "t/a" else send(msg)  # type: ignore[method-assign]
    bus.write(writer, b"2")  # lost on the link
    bus.send = send  # type: ignore[method-assign]
    bus.run_for(1.0)
    assert w.heartbeats > before
    assert [info.seq for _, info in reader.delivered] == [1, 2, 3]
    assert w.stats().retransmitted == 1


def test_the_reader_measures_each_writers_round_trip_from_its_resends() -> None:
    """The NACK -> resend round trip the QoS loop reads a robot's link from: none while nothing
    was resent, then close to the link's two delays (2 x 5 ms) once the link loses samples."""
    qos = QosProfile(history=HistoryPolicy.KEEP_ALL, max_samples=1000)
    bus, _ = world(11, Link(loss=0.0, delay_s=0.005))
    writer = bus.add(WriterMachine("t/a", qos, new_guid(), bus.clock))
    reader = bus.add(ReaderMachine("t/a", qos, new_guid(), bus.clock))
    r = reader.machine
    assert isinstance(r, ReaderMachine)
    publish(bus, writer, 20, 0.01)
    bus.run_for(0.5)
    assert r.round_trips() == {}
    bus.link.loss = 0.2
    publish(bus, writer, 200, 0.01)
    bus.run_for(2.0)
    rtt = r.round_trips()["t/a"]
    assert 0.009 <= rtt <= 0.05, rtt


def _streaming(reader_qos: QosProfile, backoff: int = 1) -> tuple[LossyBus, Node, Node]:
    qos = QosProfile(
        history=HistoryPolicy.KEEP_ALL,
        max_samples=1000,
        heartbeat_period_s=0.1,
        piggyback_heartbeats=True,
        heartbeat_backoff=backoff,
    )
    bus, _ = world(1, Link(delay_s=0.001))
    writer = bus.add(WriterMachine("t/a", qos, new_guid(), bus.clock))
    reader = bus.add(ReaderMachine("t/a", reader_qos, new_guid(), bus.clock))
    bus.run_for(0.3)
    return bus, writer, reader


def _recover_a_lost_last_sample(bus: LossyBus, writer: Node, reader: Node, within_s: float) -> None:
    """The stream stops and its last sample is lost on the link: only a heartbeat reveals it."""
    expected = len(reader.delivered) + 1
    bus.link = Link(loss=1.0, delay_s=0.001)
    bus.write(writer, b"last")
    bus.link = Link(delay_s=0.001)
    lost_at = bus.clock.now_s
    while len(reader.delivered) < expected:
        bus.step()
        assert bus.clock.now_s - lost_at < within_s, "the lost last sample was never announced"
    assert reader.delivered[-1][0] == b"last"


def test_a_streaming_writer_lets_its_data_carry_the_heartbeat() -> None:
    """At 100 Hz with a 0.1 s heartbeat, a DATA asking for an acknowledgement does each
    period's heartbeat: almost no heartbeat messages, yet the history is acknowledged as it
    goes and a lost last sample is still recovered within two periods."""
    bus, writer, reader = _streaming(QosProfile(heartbeat_period_s=0.1))
    w = writer.machine
    assert isinstance(w, WriterMachine)
    before = w.heartbeats
    publish(bus, writer, 200, 0.01)
    assert w.heartbeats - before <= 3, "a streaming writer still sent periodic heartbeats"
    assert w.heartbeats_piggybacked >= 15
    assert w.acknowledged_through() >= 190, "acknowledgements stopped with the heartbeats"
    # the stream stops, and its last sample is lost on the link
    _recover_a_lost_last_sample(bus, writer, reader, within_s=0.25)


def test_a_best_effort_reader_keeps_the_periodic_heartbeat() -> None:
    """Best-effort readers never answer an acknowledgement request: only heartbeats tell them
    the tail, so a writer with one keeps sending them."""
    bus, writer, _ = _streaming(
        QosProfile(reliability=ReliabilityPolicy.BEST_EFFORT, heartbeat_period_s=0.1)
    )
    w = writer.machine
    assert isinstance(w, WriterMachine)
    before = w.heartbeats
    publish(bus, writer, 100, 0.01)
    assert w.heartbeats_piggybacked == 0
    assert w.heartbeats - before >= 9


def test_an_unacknowledged_request_keeps_the_heartbeat() -> None:
    """Where the DATA asking for an acknowledgement (or its answer) is lost, nothing proves the
    reader knows the stream: the periodic heartbeat goes as before."""
    bus, writer, _ = _streaming(QosProfile(heartbeat_period_s=0.1))
    w = writer.machine
    assert isinstance(w, WriterMachine)
    publish(bus, writer, 50, 0.01)  # clean: the data carries the heartbeat
    before, piggybacked = w.heartbeats, w.heartbeats_piggybacked
    bus.link = Link(loss=1.0, delay_s=0.001)  # nothing gets through, either way
    publish(bus, writer, 50, 0.01)
    assert w.heartbeats - before >= 4
    # at most the first period, whose request went out (and was answered) before the loss
    assert w.heartbeats_piggybacked <= piggybacked + 1


def test_a_link_that_loses_keeps_every_heartbeat() -> None:
    """Once a reader NACKs, the writer sends every periodic heartbeat for a while even though
    its data asks for acknowledgements: a heartbeat also prompts the reader to NACK again what
    it still misses."""
    bus, writer, _ = _streaming(QosProfile(heartbeat_period_s=0.1))
    w = writer.machine
    assert isinstance(w, WriterMachine)
    bus.link = Link(loss=0.2, delay_s=0.001)
    before = w.heartbeats
    publish(bus, writer, 200, 0.01)
    assert w.nacks > 0
    assert w.heartbeats - before >= 17, "a lossy link lost its heartbeats to the piggyback"


def test_a_calm_stream_lengthens_its_heartbeat_period_up_to_the_backoff() -> None:
    """While the reader answers every request, each period doubles (up to 8 x 0.1 s here): the
    reader sends a fraction of the ACKNACKs, the history is still acknowledged as it goes, and a
    lost last sample is recovered within two grown periods."""
    acks = {}
    for backoff in (1, 8):
        bus, writer, reader = _streaming(QosProfile(heartbeat_period_s=0.1), backoff)
        r = reader.machine
        w = writer.machine
        assert isinstance(r, ReaderMachine) and isinstance(w, WriterMachine)
        before = r.acks
        publish(bus, writer, 400, 0.01)  # 4 s at 100 Hz
        acks[backoff] = r.acks - before
        assert w.heartbeats <= 3 and w.acknowledged_through() >= 300, backoff
        _recover_a_lost_last_sample(bus, writer, reader, within_s=2 * 0.8 + 0.1)
    # fixed: one request a period (about 40); grown: 0.1 + 0.2 + 0.4, then one each 0.8 s
    assert acks[1] >= 35, acks
    assert acks[8] <= acks[1] / 3, acks


def test_a_quiet_writer_sleeps_until_it_writes_again() -> None:
    """A writer that wrote nothing since its timer last fired and has nothing to announce
    (everything acknowledged) sleeps up to QUIET_HEARTBEAT_S: a robot keeps about ten writers,
    mostly quiet at low rates, and each woke its driver at every heartbeat period. Its next
    write re-arms the timer within the (grown) period, so a lost last sample is still
    recovered within two of them."""
    for backoff, longest in ((1, 0.1), (8, 0.8)):
        bus, writer, reader = _streaming(QosProfile(heartbeat_period_s=0.1), backoff)
        w = writer.machine
        assert isinstance(w, WriterMachine)
        publish(bus, writer, 3, 0.01)
        gaps = []
        for _ in range(300):  # 3 s, nothing written
            bus.run_for(0.01)
            gaps.append(w.next_heartbeat_s - bus.clock.now_s)
        assert max(gaps) == pytest.approx(QUIET_HEARTBEAT_S, abs=0.011), backoff
        assert w.quiet and len(reader.delivered) == 3
        bus.write(writer, b"again")
        assert not w.quiet
        assert w.next_heartbeat_s - bus.clock.now_s <= longest + 1e-6, backoff
        bus.run_for(0.05)
        assert reader.delivered[-1][0] == b"again"
        _recover_a_lost_last_sample(bus, writer, reader, within_s=2 * longest + 0.1)


def test_a_writer_on_a_link_that_lost_something_keeps_its_heartbeats() -> None:
    """After a reader's NACK the link counts as lossy for LOSSY_HOLD_PERIODS periods: an idle
    writer's heartbeats keep their period then (a lost sample is announced within one), and it
    goes quiet only once the link has been clean that long."""
    bus, writer, reader = _streaming(QosProfile(heartbeat_period_s=0.1))
    w = writer.machine
    assert isinstance(w, WriterMachine)
    publish(bus, writer, 3, 0.01)
    _recover_a_lost_last_sample(bus, writer, reader, within_s=2 * 0.1 + 0.1)
    assert w.nacks >= 1
    gaps = []
    for _ in range(200):  # 2 s idle, within the 5 s hold
        bus.run_for(0.01)
        gaps.append(w.next_heartbeat_s - bus.clock.now_s)
    assert not w.quiet and max(gaps) <= 0.1 + 1e-6
    bus.run_for(LOSSY_HOLD_PERIODS * 0.1)
    assert w.quiet


def test_a_quiet_writer_wakes_for_a_new_reader_and_its_liveliness_lease() -> None:
    """Quiet is only for a writer with nothing to say: a reader that matches re-arms the timer
    (its heartbeats come at the period while it catches up), and a liveliness lease is still
    asserted every lease / 4."""
    bus, writer, _ = _streaming(QosProfile(heartbeat_period_s=0.1))
    w = writer.machine
    assert isinstance(w, WriterMachine)
    publish(bus, writer, 3, 0.01)
    bus.run_for(2.0)
    assert w.quiet
    bus.add(ReaderMachine("t/a", QosProfile(heartbeat_period_s=0.1), new_guid(), bus.clock))
    while len(w.proxies) < 2:
        bus.step()
    assert not w.quiet and w.next_heartbeat_s - bus.clock.now_s <= 0.1 + 1e-6

    qos = QosProfile(heartbeat_period_s=0.1, lease_duration_s=2.0)
    lease_bus, _ = world(1, Link(delay_s=0.001))
    leased = lease_bus.add(WriterMachine("t/l", qos, new_guid(), lease_bus.clock))
    lease_bus.add(
        ReaderMachine("t/l", QosProfile(heartbeat_period_s=0.1), new_guid(), lease_bus.clock)
    )
    lease_bus.run_for(0.3)
    lw = leased.machine
    assert isinstance(lw, WriterMachine)
    publish(lease_bus, leased, 3, 0.01)
    before = lw.heartbeats
    gaps = []
    for _ in range(400):  # 4 s, nothing written: quiet between the lease's heartbeats
        lease_bus.run_for(0.01)
        gaps.append(lw.next_heartbeat_s - lease_bus.clock.now_s)
    assert max(gaps) <= 0.5 + 0.011
    assert 7 <= lw.heartbeats - before <= 9  # every 0.5 s


def test_a_late_reader_keeps_a_grown_period_and_its_nack_ends_it() -> None:
    """A request unanswered is a reader behind as often as a lost sample: the grown period
    holds, and the heartbeats it sends make a reader that misses something NACK, which brings
    the base period back. Falling back on every late answer fed a CEDDP behind 50 robots more
    heartbeats and ACKNACKs (820-1 119 samples/s against 2 880-4 139 holding; issue 17)."""
    bus, writer, reader = _streaming(QosProfile(heartbeat_period_s=0.1), backoff=8)
    w = writer.machine
    assert isinstance(w, WriterMachine)
    publish(bus, writer, 300, 0.01)  # calm: the period grew to 0.8 s
    bus.link = Link(loss=1.0, delay_s=0.001)  # the reader hears nothing and answers nothing
    before = w.heartbeats
    publish(bus, writer, 300, 0.01)  # 3 s: 2-4 heartbeats at 0.8 s, about 25 at 0.1 s
    assert 1 <= w.heartbeats - before <= 4, "the grown period fell back without a NACK"
    bus.link = Link(delay_s=0.001)
    while w.nacks == 0:  # the next heartbeat reveals the 300 samples: the reader NACKs them
        bus.step()
    assert w.next_heartbeat_s - bus.clock.now_s <= 0.1 + 1e-6
    bus.run_for(1.0)
    assert len(reader.delivered) == 600


def test_a_nack_brings_a_grown_heartbeat_period_back() -> None:
    """A link that starts losing after a calm stream gets its heartbeats at the base period at
    once, as a fixed period's would (test_a_link_that_loses_keeps_every_heartbeat)."""
    bus, writer, _ = _streaming(QosProfile(heartbeat_period_s=0.1), backoff=8)
    w = writer.machine
    assert isinstance(w, WriterMachine)
    publish(bus, writer, 300, 0.01)  # calm: the period grew to 0.8 s
    i = 0
    while w.next_heartbeat_s - bus.clock.now_s < 0.7:  # the grown timer just fired
        bus.write(writer, b"%d" % i)
        bus.run_for(0.01)
        i += 1
    bus.link = Link(loss=1.0, delay_s=0.001)  # one sample lost: the next one reveals the gap
    bus.write(writer, b"lost")
    bus.link = Link(delay_s=0.001)
    while w.nacks == 0:
        bus.write(writer, b"%d" % i)
        bus.run_for(0.001)
        i += 1
        assert i < 1000, "the gap was never NACKed"
    assert w.next_heartbeat_s - bus.clock.now_s <= 0.1 + 1e-6, "the grown period held on"
    bus.link = Link(loss=0.2, delay_s=0.001)
    before = w.heartbeats
    publish(bus, writer, 200, 0.01)
    assert w.heartbeats - before >= 15, "a lossy link kept the calm stream's long period"


def test_a_tick_polls_every_writers_timers_once_a_period_not_at_every_tick() -> None:
    """The fine timer ticks every few ms while any writer is busy; polling all of a CEDDP's
    writers' deadlines and leases each time grew with the fleet (400 us a tick at 400 writers,
    benchmarks/investigations/reader_busy.py). Every writer is polled once a full period (50 ms
    at most)."""
    bus, _ = world(1, Link(delay_s=0.001))
    qos = QosProfile(history=HistoryPolicy.KEEP_ALL, deadline_s=0.2)
    for t in range(50):
        bus.add(WriterMachine(f"f/r/t{t}", qos, new_guid(), bus.clock))
    reader = bus.add(ReaderMachine("f/r/*", qos, new_guid(), bus.clock))
    bus.run_for(0.3)
    r = reader.machine
    assert isinstance(r, ReaderMachine) and len(r.writers) == 50
    polled: list[str] = []
    poll = r._poll_timers

    def counting(p: Any, now: float, actions: list[Any]) -> None:
        polled.append(p.hex)
        poll(p, now, actions)

    r._poll_timers = counting  # type: ignore[method-assign]
    bus.run_for(0.2)  # 200 ticks of 1 ms
    periods = 0.2 / r._full_period_s
    assert 50 * periods <= len(polled) <= 50 * (periods / 0.8 + 1), len(polled)
    # and the deadline is still noticed: the writers wrote nothing for 0.5 s
    assert r.stats().deadline_missed >= 50


def test_a_writer_that_leaves_with_a_gap_is_unmatched_once_and_its_slot_can_be_reused() -> None:
    """A writer announces samples the reader never got, then dies: at its departure the reader
    counts them lost (the skip makes the writer a suspect again). That stale suspect was deleted
    a second time at the next fine tick: a KeyError that ended the CEDDP's channel thread, and
    with it every robot's reports on that reader (a 50-robot fleet under overload, issue 17)."""
    bus, clock = world(1, Link())
    qos = QosProfile(depth=20)
    guid = new_guid()
    writer = bus.add(WriterMachine("t/a", qos, guid, clock))
    # its state is kept 0.5 s in case it comes back (a session lost, issue 39), then forgotten
    reader = bus.add(ReaderMachine("t/a", qos, new_guid(), clock, away_retention_s=0.5))
    bus.run_for(0.3)
    publish(bus, writer, 5, 0.001)
    bus.run_for(0.1)
    r, w = reader.machine, writer.machine
    assert isinstance(r, ReaderMachine) and isinstance(w, WriterMachine)
    for i in range(5):  # written, never on the link
        _, _, actions = w.write(b"lost %d" % i)
        bus.run(writer, actions)
    proxy = r.writers[("t/a", guid)]
    for _ in range(2000):  # until a heartbeat announces them
        bus.step()
        if proxy.highest >= 10:
            break
    assert proxy.highest >= 10 and proxy.expected <= 10
    bus.remove(writer)  # before it can answer a NACK
    bus.run_for(0.3)  # away: it may come back, nothing is lost yet, and it is still accounted
    assert ("t/a", guid) not in r.writers and proxy not in r._suspects
    assert r.stats().away == 1 and r.stats().lost == 0
    assert r.accounted()[w.hex][1] == 5
    bus.run_for(1.0)  # before the fix: a stale suspect (busy != busy_scan), then a KeyError
    assert ("t/a", guid) not in r.writers and proxy not in r._suspects
    assert r.stats().away == 0 and w.hex not in r.accounted()
    seqs = [info.seq for _, info in reader.delivered]
    assert len(seqs) + r.stats().lost == 10, (seqs, r.stats())
    # the same writer comes back (a token flap after the unmatch): a new proxy, left alone
    again = bus.add(WriterMachine("t/a", qos, guid, clock))
    bus.run_for(0.3)
    assert r.writers[("t/a", guid)] is not proxy
    bus.run_for(0.5)
    assert ("t/a", guid) in r.writers
    bus.remove(again)


def test_the_ack_epoch_moves_whenever_acknowledged_through_does() -> None:
    """``Writer.acknowledged_through`` keeps its last figure while the machine's ``ack_epoch``
    stands: every change of the figure but a write without reliable readers must move the
    epoch. Checked at every step of a lossy KEEP_LAST run (ACKNACKs, overwrites that move a
    reader on, GAPs), a second reader matching and both leaving."""
    bus, _ = world(11, Link(loss=0.2, delay_s=0.003))
    writer = bus.add(WriterMachine("t/a", QosProfile(depth=2), new_guid(), bus.clock))
    first = bus.add(ReaderMachine("t/a", QosProfile(depth=2), new_guid(), bus.clock))
    w = writer.machine
    assert isinstance(w, WriterMachine)
    kept = (-1, 0)  # (epoch, figure) as a Writer keeps them
    checked = 0

    def check() -> None:
        nonlocal kept, checked
        epoch, figure = kept
        if w.ack_epoch == epoch and w.n_reliable:
            assert figure == w.acknowledged_through(), (epoch, figure, w.acknowledged_through())
            checked += 1
        else:
            kept = (w.ack_epoch, w.acknowledged_through())

    bus.run_for(0.3)
    second = None
    for i in range(1500):
        bus.write(writer, b"%d" % i)
        check()
        if i == 500:
            second = bus.add(ReaderMachine("t/a", QosProfile(depth=2), new_guid(), bus.clock))
        if i == 1000:
            bus.remove(first)
        if i % 3 == 0:
            bus.step(0.0005)
            check()
    assert second is not None
    bus.run_for(1.0)
    check()
    bus.remove(second)
    bus.run_for(0.1)  # the reader's token goes on the bus
    assert w.n_reliable == 0
    bus.write(writer, b"after")  # no reliable reader: the figure is every write's
    check()
    assert w.acknowledged_through() == w.last_seq
    assert checked > 300, checked  # steps where the kept figure was the one returned


# ---------------------------------------------------------------- a session lost and back


def _partitioned_run(
    seed: int, link: Link, qos: QosProfile, before: int, during: int, after: int, gap_s: float
) -> tuple[Node, Node, LossyBus, bool]:
    """A writer loses its session for ``gap_s`` (longer than the token's departure takes) while
    it goes on writing, then comes back with the same guid: a dead zone or a roam. The last
    item: whether the reader knew where the match stood when the session went (a heartbeat or a
    sample of the writer had reached it; on a lossy link neither may have)."""
    bus, clock = world(seed, link)
    writer = bus.add(WriterMachine("t/a", qos, new_guid(), clock))
    reader = bus.add(ReaderMachine("t/a", qos, new_guid(), clock))
    bus.run_for(0.05)
    publish(bus, writer, before, 0.002)
    bus.run_for(0.05)
    r = reader.machine
    assert isinstance(r, ReaderMachine)
    synced = any(proxy.synced for proxy in r.writers.values())
    bus.partition(writer)
    w = writer.machine
    assert isinstance(w, WriterMachine)
    for i in range(during):  # a KEEP_ALL writer with no reader matched always has room
        bus.write(writer, b"%d" % (before + i))
        bus.run_for(gap_s / max(during, 1))
    bus.run_for(gap_s / 2)
    bus.heal(writer)
    publish_from(bus, writer, before + during, after, 0.002)
    bus.run_for(2.0)
    return reader, writer, bus, synced


def publish_from(bus: LossyBus, writer: Node, first: int, n: int, period_s: float) -> None:
    w = writer.machine
    assert isinstance(w, WriterMachine)
    for i in range(first, first + n):
        while not w.has_room():
            bus.step()
        bus.write(writer, b"%d" % i)
        bus.run_for(period_s)


@FAST
@given(
    seed=st.integers(0, 2**32),
    link=links,
    qos=qos_choices,
    before=st.integers(1, 60),
    during=st.integers(0, 60),
    after=st.integers(1, 30),
    gap_s=st.sampled_from([0.3, 1.0]),
)
def test_a_writer_whose_session_is_lost_resumes_its_match_and_nothing_is_delivered_twice(
    seed: int, link: Link, qos: QosProfile, before: int, during: int, after: int, gap_s: float
) -> None:
    """Issue 39: a dead zone longer than Zenoh's lease ended the robot's session; when it was
    back, its writers' history was taken again as a new match (14 331 sent, 17 218 received).
    The match resumes: every seq of it is delivered once or counted lost, on one proxy."""
    reader, writer, _, synced = _partitioned_run(seed, link, qos, before, during, after, gap_s)
    r, w = reader.machine, writer.machine
    assert isinstance(r, ReaderMachine) and isinstance(w, WriterMachine)
    seqs = check_invariant(reader, writer)
    assert r.match_start(w.hex) == 1
    # a reader that knew nothing of the match when the session went has nothing to resume: the
    # writer's return is its first match (hypothesis found it: 50 % loss, one sample before)
    assert r.stats().resumed == int(synced) and w.stats().resumed == 1
    assert r.stats().matched == 1 and w.stats().matched == 1
    if (
        qos.reliable
        and qos.history is HistoryPolicy.KEEP_ALL
        and link.loss == 0
        and before + during < qos.capacity
    ):
        # nothing lost on the link and the history held the gap: it is resent in full
        assert seqs == list(range(1, w.last_seq + 1))


def test_a_session_loss_without_retention_delivered_the_history_twice() -> None:
    """The failure the retention removes, shown with it off (a reader that forgets at once):
    the same TRANSIENT_LOCAL writer coming back is taken as a new match and its history is
    delivered again."""
    qos = QosProfile(durability=DurabilityPolicy.TRANSIENT_LOCAL, depth=50)
    bus, clock = world(3, Link())
    writer = bus.add(WriterMachine("t/a", qos, new_guid(), clock, away_retention_s=0.0))
    reader = bus.add(ReaderMachine("t/a", qos, new_guid(), clock, away_retention_s=0.0))
    bus.run_for(0.05)
    publish(bus, writer, 10, 0.002)
    bus.run_for(0.1)
    bus.partition(writer)
    bus.run_for(0.5)
    bus.heal(writer)
    bus.run_for(1.0)
    seqs = [info.seq for _, info in reader.delivered]
    assert len(seqs) > len(set(seqs))  # the old behaviour: every sample twice


def test_a_reader_that_remembers_a_writer_that_forgot_counts_the_gap_lost() -> None:
    """The writer's retention ran out (it forgot the reader) but the reader's did not: the
    writer matches the reader as new (VOLATILE: from its next seq), and the seqs written while
    the reader was away are GAPed and counted lost, never left open."""
    qos = QosProfile(depth=5)
    bus, clock = world(4, Link())
    writer = bus.add(WriterMachine("t/a", qos, new_guid(), clock, away_retention_s=0.1))
    reader = bus.add(ReaderMachine("t/a", qos, new_guid(), clock))
    bus.run_for(0.05)
    publish(bus, writer, 10, 0.002)
    bus.run_for(0.1)
    bus.partition(writer)
    for i in range(20):
        bus.write(writer, b"%d" % (10 + i))
        bus.run_for(0.02)
    bus.heal(writer)
    bus.run_for(0.05)  # the match is made again before the next writes
    publish_from(bus, writer, 30, 5, 0.002)
    bus.run_for(2.0)
    r, w = reader.machine, writer.machine
    assert isinstance(r, ReaderMachine) and isinstance(w, WriterMachine)
    seqs = check_invariant(reader, writer)
    assert r.stats().resumed == 1 and w.stats().resumed == 0
    assert seqs[:10] == list(range(1, 11)) and seqs[-5:] == list(range(31, 36))
    assert r.stats().lost == 20
