"""A reader behind a FIFO: heartbeats reach the machine straight away (their subscription calls
back), data wait in the channel's FIFO. What the FIFO still holds is not lost, so a NACK for it
waits until the channel says the FIFO drained past the heartbeat (``ReaderMachine.drained``).
Without that wait a CEDDP behind on its sensor FIFO NACKed what it had not read yet (issue 17:
``python benchmarks/ceddp_ingest.py`` printed 52 000-223 000 duplicates of 200 000 samples)."""

from __future__ import annotations

import math
import random

from arpz.core.protocol._common import new_guid
from arpz.core.protocol.actions import Send
from arpz.core.protocol.qos import HistoryPolicy, QosProfile
from arpz.core.protocol.reader_machine import ReaderMachine
from arpz.core.protocol.timers import FakeClock
from arpz.core.protocol.writer_machine import WriterMachine
from tests.unit.reliability.lossy_bus import Link, LossyBus, Node

QOS = QosProfile(history=HistoryPolicy.KEEP_ALL, max_samples=1000, batch_max_samples=1)
N = 50


def _behind_a_fifo(drained_s: float, behind: bool = True) -> tuple[LossyBus, Node, list[Send]]:
    """A reader matched to a writer that then wrote N samples. The data (not the heartbeats)
    are held back in ``fifo`` as a channel's FIFO holds them; the reader last saw that FIFO
    empty at ``drained_s``, and its delivery thread is ``behind`` on it (more than one message
    a pull) or not."""
    bus = LossyBus(random.Random(1), Link(), FakeClock())
    writer = bus.add(WriterMachine("t/a", QOS, new_guid(), bus.clock))
    reader = bus.add(ReaderMachine("t/a", QOS, new_guid(), bus.clock))
    bus.run_for(0.2)  # matched and synced
    r = reader.machine
    assert isinstance(r, ReaderMachine)
    assert r.writers and all(p.synced for p in r.writers.values())
    fifo: list[Send] = []
    send = bus.send
    bus.send = lambda msg: fifo.append(msg) if msg.key == "t/a" else send(msg)  # type: ignore[method-assign]
    r.drained_s = drained_s
    r.fifo_behind = behind
    for i in range(N):
        bus.write(writer, b"%d" % i)
    bus.run_for(0.5)  # heartbeats announce all N; the data sit in the FIFO
    bus.send = send  # type: ignore[method-assign]
    return bus, reader, fifo


def _read(bus: LossyBus, reader: Node, fifo: list[Send], skip: int | None = None) -> None:
    """The delivery thread takes the FIFO in, then finds it empty."""
    r = reader.machine
    assert isinstance(r, ReaderMachine)
    empty_at = bus.clock.monotonic_s()
    for i, msg in enumerate(fifo):
        if i != skip:
            bus.run(reader, r.on_data(msg.key, msg.payload, msg.attachment))
    if r.drained(empty_at):
        bus.run(reader, r.tick())


def test_a_heartbeat_ahead_of_queued_data_asks_for_nothing() -> None:
    bus, reader, fifo = _behind_a_fifo(drained_s=0.0)
    r = reader.machine
    assert isinstance(r, ReaderMachine)
    assert len(fifo) == N
    assert r.stats().nacks == 0, "NACKed samples that were only queued"
    assert r.drain_waited
    _read(bus, reader, fifo)
    bus.run_for(0.5)
    assert [i.seq for _, i in reader.delivered] == list(range(1, N + 1))
    stats = r.stats()
    assert (stats.nacks, stats.duplicates, stats.lost) == (0, 0, 0)
    assert not r.drain_waited


def test_without_the_fifo_s_word_the_same_reader_asks_for_everything_queued() -> None:
    """The same scenario with no FIFO information (``drained_s`` inf, as for a reader fed by
    callbacks): the heartbeat's announced seqs look lost and are NACKed, then arrive twice."""
    bus, reader, fifo = _behind_a_fifo(drained_s=math.inf)
    r = reader.machine
    assert isinstance(r, ReaderMachine)
    assert r.stats().nacks > 0
    _read(bus, reader, fifo)
    bus.run_for(0.5)
    assert r.stats().duplicates > 0


def test_a_sample_really_lost_is_asked_for_once_the_fifo_drained() -> None:
    bus, reader, fifo = _behind_a_fifo(drained_s=0.0)
    r = reader.machine
    assert isinstance(r, ReaderMachine)
    _read(bus, reader, fifo, skip=N // 2)  # lost on the link: never in the FIFO
    assert r.stats().nacks == 1, "the NACK goes out as soon as the FIFO has drained"
    bus.run_for(0.2)
    assert [i.seq for _, i in reader.delivered] == list(range(1, N + 1))
    stats = r.stats()
    assert (stats.retransmitted, stats.duplicates, stats.lost) == (1, 0, 0)


def test_a_fifo_that_never_drains_costs_an_acknack_a_heartbeat_not_one_a_tick() -> None:
    """While a NACK waits for a drain that does not come (a FIFO that never empties), the
    reader answers each heartbeat and re-checks once a heartbeat period: not at every tick of
    its fine timer (1 ms here), which would flood the writer with ACKNACKs."""
    bus, reader, _ = _behind_a_fifo(drained_s=0.0)
    r = reader.machine
    assert isinstance(r, ReaderMachine)
    before = r.stats().acks
    bus.run_for(1.0)
    periods = 1.0 / QOS.heartbeat_period_s
    assert 0 < r.stats().acks - before <= 2 * periods + 2
    assert r.stats().nacks == 0


def test_a_reader_keeping_up_with_its_fifo_asks_at_once() -> None:
    """A delivery thread that finds one message a pull is not behind: a gap is NACKed after
    nack_delay_s, as with no FIFO at all, not held for a drain. Held, the recovery of every real
    loss on a lossy link waited for a pass of the delivery thread (benchmarks/RESULTS.md)."""
    _, reader, _ = _behind_a_fifo(drained_s=0.0, behind=False)
    r = reader.machine
    assert isinstance(r, ReaderMachine)
    assert r.stats().nacks > 0
    assert not r.drain_waited
