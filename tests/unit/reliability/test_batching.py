"""Write batching: many samples in one Zenoh message, each handled as if it came alone."""

from __future__ import annotations

import random

from hypothesis import given
from hypothesis import strategies as st

from arpz.channel import Writer
from arpz.core.protocol import wire
from arpz.core.protocol._common import new_guid
from arpz.core.protocol.actions import Send
from arpz.core.protocol.qos import HistoryPolicy, QosProfile
from arpz.core.protocol.reader_machine import ReaderMachine
from arpz.core.protocol.timers import FakeClock
from arpz.core.protocol.writer_machine import BATCH_MAX_BYTES, WriterMachine
from arpz.transport.memory import MemoryBus, MemoryTransport
from tests.unit.reliability.lossy_bus import Link, LossyBus, publish

G = b"\x07" * 8
BATCHED = QosProfile(history=HistoryPolicy.KEEP_ALL, batch_max_samples=4, batch_max_delay_s=0.002)


def record_sends(bus: LossyBus) -> list[Send]:
    """Every message the machines put on the bus, before the bus loses any."""
    sent: list[Send] = []
    original = bus.send
    bus.send = lambda msg: (sent.append(msg), original(msg))[1]  # type: ignore[method-assign]
    return sent


def test_a_batch_roundtrips_and_is_never_taken_for_a_single_sample() -> None:
    payload, attachment = wire.encode_batch(
        wire.F_ACK_REQUEST, G, 7, [b"a", b"", b"ccc"], [10, 11, -12]
    )
    assert payload == b"accc" and len(attachment) != wire.DATA.size
    assert wire.decode_data(attachment) is None
    batch = wire.decode_batch(payload, attachment)
    assert batch == wire.Batch(
        wire.F_ACK_REQUEST | wire.F_BATCH, G, 7, (10, 11, -12), [b"a", b"", b"ccc"]
    )


@given(
    samples=st.lists(
        st.tuples(st.binary(max_size=8), st.integers(-(2**63), 2**63 - 1)), min_size=1, max_size=5
    ),
    cut=st.integers(0, 200),
    flip=st.integers(0, 200),
    xor=st.integers(1, 255),
    extra=st.binary(max_size=3),
)
def test_a_damaged_batch_is_refused_whole(
    samples: list[tuple[bytes, int]], cut: int, flip: int, xor: int, extra: bytes
) -> None:
    payloads, stamps = [d for d, _ in samples], [s for _, s in samples]
    payload, attachment = wire.encode_batch(0, G, 1, payloads, stamps)
    damaged = bytearray(attachment)
    damaged[flip % len(damaged)] ^= xor
    # lengths that cannot add up are always refused
    assert wire.decode_batch(payload, attachment[: cut % len(attachment)]) is None
    assert wire.decode_batch(payload + extra + b"x", attachment) is None
    assert wire.decode_batch(payload[:-1] if payload else b"x", attachment) is None
    # a flipped byte may land in a stamp or the guid: then it still decodes, consistently
    batch = wire.decode_batch(payload, bytes(damaged))
    if batch is not None:
        assert b"".join(batch.payloads) == payload and len(batch.stamps) == len(samples)
        assert len(damaged) == wire.BATCH.size + len(batch.payloads) * wire.BATCH_ENTRY_SIZE


def test_the_writer_sends_alone_after_a_pause_and_batches_a_burst() -> None:
    clock = FakeClock()
    w = WriterMachine("t/a", BATCHED, new_guid(), clock)
    _, ready, _ = w.write(b"0")
    assert ready is not None and len(ready[1]) == wire.DATA.size  # first after a pause: at once
    outs = [w.write(b"%d" % i)[1] for i in range(1, 5)]
    assert outs[:3] == [None, None, None] and outs[3] is not None  # full at 4
    batch = wire.decode_batch(*outs[3])
    assert batch is not None and batch.first == 2
    assert batch.payloads == [b"1", b"2", b"3", b"4"]
    assert w.write(b"5")[1] is None  # 0 s since the last put: joins a new batch
    assert w.flush_batch(force=False) is None  # not yet due
    hb = [a for a in w.tick() if isinstance(a, Send) and "/hb/" in a.key]
    assert wire.decode_heartbeat(hb[0].payload).last == 5  # type: ignore[union-attr]
    clock.advance(0.0025)
    sends = [a for a in w.tick() if isinstance(a, Send)]
    assert sends and sends[0].key == "t/a" and wire.decode_data(sends[0].attachment) is not None
    assert not w.batch and w.busy()  # it just put: streaming, the driver keeps its fine tick
    clock.advance(0.0025)
    assert not w.busy()  # quiet for a whole batch delay: the driver may sleep


def test_a_sample_that_would_overflow_the_size_cap_starts_the_next_batch() -> None:
    clock = FakeClock()
    qos = QosProfile(history=HistoryPolicy.KEEP_ALL, batch_max_samples=64)
    w = WriterMachine("t/a", qos, new_guid(), clock)
    w.write(b"first")  # alone, at once
    half = b"h" * (BATCH_MAX_BYTES // 2)
    assert w.write(half)[1] is None and w.write(half)[1] is not None  # exactly the cap: full
    assert w.write(b"a")[1] is None  # opens a batch of one small sample
    seq, ready, _ = w.write(b"b" * BATCH_MAX_BYTES)  # would make it 1 byte too big
    assert ready is not None
    batch = wire.decode_data(ready[1])  # the open batch went out alone, without this sample
    assert batch is not None and batch.seq == seq - 1 and ready[0] == b"a"
    assert w.batch == [b"b" * BATCH_MAX_BYTES]  # which opened the next batch
    clock.advance(2 * qos.batch_max_delay_s)
    ready = w.flush_batch(force=False)
    assert ready is not None and wire.decode_data(ready[1]).seq == seq  # type: ignore[union-attr]


def test_a_batch_reaches_the_reader_as_single_samples_in_order() -> None:
    bus = LossyBus(random.Random(1), Link(), FakeClock())
    writer = bus.add(WriterMachine("t/a", BATCHED, new_guid(), bus.clock))
    reader = bus.add(ReaderMachine("t/*", BATCHED, new_guid(), bus.clock))
    sent = record_sends(bus)
    bus.run_for(0.3)
    for i in range(5):  # one alone (after a pause), then one full batch of 4
        bus.write(writer, b"%d" % i)
    bus.run_for(0.1)
    data = [m for m in sent if m.key == "t/a"]
    assert [len(m.attachment or b"") == wire.DATA.size for m in data] == [True, False]
    assert [info.seq for _, info in reader.delivered] == [1, 2, 3, 4, 5]
    assert [p for p, _ in reader.delivered] == [b"0", b"1", b"2", b"3", b"4"]
    r = reader.machine
    assert isinstance(r, ReaderMachine) and r.lost == 0 and r.duplicates == 0


def test_over_a_lossy_bus_batches_form_and_keep_all_still_delivers_everything() -> None:
    bus = LossyBus(random.Random(3), Link(loss=0.2, jitter_s=0.002), FakeClock())
    qos = QosProfile(history=HistoryPolicy.KEEP_ALL, max_samples=200, batch_max_samples=16)
    writer = bus.add(WriterMachine("t/a", qos, new_guid(), bus.clock))
    reader = bus.add(ReaderMachine("t/a", qos, new_guid(), bus.clock))
    sent = record_sends(bus)
    bus.run_for(0.3)
    publish(bus, writer, 300, 0.0)  # as fast as possible: batches fill
    bus.run_for(3.0)
    data = [m for m in sent if m.key == "t/a"]
    assert len(data) < 300 / 4, f"{len(data)} messages for 300 samples: batches did not form"
    seqs = [info.seq for _, info in reader.delivered]
    assert seqs == list(range(1, 301))
    assert [p for p, _ in reader.delivered] == [b"%d" % i for i in range(300)]


def test_heartbeats_stay_well_formed_when_the_history_holds_only_unsent_samples() -> None:
    """KEEP_LAST depth 1 with a batch open: the history's only sample is not yet sent."""
    clock = FakeClock()
    qos = QosProfile(depth=1, batch_max_samples=8, batch_max_delay_s=0.01)
    w = WriterMachine("t/a", qos, new_guid(), clock)
    reader = new_guid()
    w.write(b"0")  # alone, at once
    w.write(b"1")  # opens a batch
    w.write(b"2")  # overwrites seq 2 in the history of depth 1
    sync = [a for a in w.on_reader_token(wire.reader_token("t/a", reader.hex(), "RVA_0_0"), True)]
    hb = [a for a in w.tick() if isinstance(a, Send) and "/hb/" in a.key]
    syncs = [wire.decode_heartbeat(a.payload) for a in sync if isinstance(a, Send)]
    beats = [wire.decode_heartbeat(a.payload) for a in hb]
    assert syncs and beats and None not in syncs + beats
    assert [(h.first, h.last) for h in syncs if h] == [(4, 3)]  # match starts at 4: nothing yet
    assert [h.last for h in beats if h] == [1]  # only seq 1 went out


def test_an_express_writer_sends_every_sample_of_a_burst_alone() -> None:
    """``express`` is the latency choice: no arpz batching either, whatever the profile says."""
    bus = MemoryBus()
    a, b = MemoryTransport(bus), MemoryTransport(bus)
    attachments: dict[bool, list[bytes | None]] = {True: [], False: []}
    for express in (True, False):
        key = f"t/{'express' if express else 'plain'}"
        b.subscribe(key, lambda _k, _p, att, e=express: attachments[e].append(att))
        # a frozen clock: every write after the first is "within the batch delay", whatever
        # the machine's load
        clock = FakeClock()
        with Writer(
            a, key, QosProfile(batch_max_samples=64), express=express, clock=clock
        ) as writer:
            assert writer.qos.batching is not express
            for i in range(200):
                writer.write(b"%d" % i)
    assert [len(att or b"") for att in attachments[True]] == [wire.DATA.size] * 200
    # one alone (nothing sent before it), three full batches of 64, the last 7 sent by close()
    assert len(attachments[False]) == 5, "the plain writer did not batch the burst"
