"""A plain Writer/Reader pair carries a sample larger than the writer's fragment size as DATA_FRAG
fragments: one seq, delivered whole once or counted lost once, only missing fragments resent."""

from __future__ import annotations

import random
from collections.abc import Callable
from contextlib import closing

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from arpz.channel import Reader, Writer
from arpz.channel.bundling import Bundler
from arpz.channel.io import Inlet, Outlet
from arpz.core.link_sizes import (
    MIN_FRAGMENT_BYTES,
    UDP_BATCH_BYTES,
    ZENOH_MESSAGE_OVERHEAD,
    LinkSizes,
    datagram_fragment_bytes,
    link_sizes,
    session_batch_size,
    writer_fragment_bytes,
)
from arpz.core.protocol import wire
from arpz.core.protocol._common import new_guid
from arpz.core.protocol.actions import Send
from arpz.core.protocol.events import DataInfo
from arpz.core.protocol.fragments import DEFAULT_FRAGMENT_BYTES, STREAM_FRAGMENT_BYTES
from arpz.core.protocol.qos import DurabilityPolicy, HistoryPolicy, QosProfile, ReliabilityPolicy
from arpz.core.protocol.reader_machine import ReaderMachine
from arpz.core.protocol.timers import FakeClock
from arpz.core.protocol.writer_machine import WriterMachine
from arpz.transport.memory import MemoryBus, MemoryTransport
from tests.support import wait_until
from tests.unit.reliability.lossy_bus import Link, LossyBus, Node
from tests.unit.reliability.test_large import LossyTransport, Sink

G1, G2 = b"\x01" * 8, b"\x02" * 8
FRAG = 100  # fragment bytes of the machines under test: a 1 000-byte sample is 10 fragments


def payload_of(i: int, size: int) -> bytes:
    return random.Random(i).randbytes(size)


# ----------------------------------------------------------------------------------- wire
def test_fragment_headers_roundtrip_and_never_share_a_length_with_other_headers() -> None:
    att = wire.encode_data_frag(wire.F_ACK_REQUEST, G1, 7, 123, 3, 1000, 100)
    h = wire.decode_frag(att)
    assert h is not None and (h.seq, h.fragment, h.total, h.chunk, h.echo) == (7, 3, 1000, 100, -1)
    assert h.flags & wire.F_FRAGMENT and h.flags & wire.F_ACK_REQUEST
    resend = wire.encode_resend_frag(G1, 7, 123, 9, 1000, 100, 42)
    r = wire.decode_frag(resend)
    assert r is not None and r.echo == 42 and r.flags & wire.F_RETRANSMIT and r.fragment == 9
    batch_lengths = {wire.BATCH.size + n * wire.BATCH_ENTRY_SIZE for n in range(1, 1025)}
    for size in (wire.DATA_FRAG.size, wire.RESEND_FRAG.size):
        assert size not in {wire.DATA.size, wire.RESEND.size} | batch_lengths
    assert wire.decode_data(att) is None and wire.decode_data(resend) is None
    # a "fragment" of a sample that fits one fragment, or past the sample's end, is refused
    assert wire.decode_frag(wire.encode_data_frag(0, G1, 7, 0, 0, 100, 100)) is None
    assert wire.decode_frag(wire.encode_data_frag(0, G1, 7, 0, 10, 1000, 100)) is None
    assert wire.decode_frag(wire.encode_data_frag(0, G1, 0, 0, 0, 1000, 100)) is None


def test_acknack_frag_roundtrips_and_plain_acknack_is_unchanged() -> None:
    plain = wire.encode_acknack(G2, G1, 4, 1, [(5, 6)])
    assert wire.control_kind(plain) == wire.KIND_ACKNACK and len(plain) == 32 + 16
    frags = ((9, 3, 3), (9, 7, 8), (12, 0, 719))
    an = wire.encode_acknack(G2, G1, 4, 1, [(5, 6)], frags)
    assert wire.control_kind(an) == wire.KIND_ACKNACK_FRAG
    assert len(an) == 32 + 16 + 2 + 3 * 16
    assert wire.decode_acknack(an) == (G2, G1, 4, 1, [(5, 6)], frags)
    assert wire.decode_acknack(an[:-1]) is None  # lengths must add up
    bad = wire.encode_acknack(G2, G1, 4, 1, [], ((9, 5, 4),))  # hi < lo
    assert wire.decode_acknack(bad) is None
    many = wire.encode_acknack(G2, G1, 4, 1, [], [(9, i, i) for i in range(100)])
    decoded = wire.decode_acknack(many)
    assert decoded is not None and len(decoded.frags) == wire.MAX_FRAG_RANGES


# ----------------------------------------------------------------------------------- sizes
def test_link_sizes_follow_the_endpoints() -> None:
    udp = LinkSizes(UDP_BATCH_BYTES, DEFAULT_FRAGMENT_BYTES)
    assert link_sizes(["udp/192.168.1.10:7447"]) == udp == (1472, 1280)
    assert link_sizes([]) == udp  # nothing known: safe on every link
    assert link_sizes(["tcp/10.0.0.1:7447", "udp/10.0.0.1:7447"]) == udp  # may go by UDP
    for streams in (["tcp/h:1"], ["tls/h:1", "quic/h:1"], ["ws/h:1", "unixsock-stream//tmp/s"]):
        assert link_sizes(streams) == (None, STREAM_FRAGMENT_BYTES)


def test_a_session_sets_the_batch_of_its_links() -> None:
    assert session_batch_size(["udp/10.0.0.1:7447"]) == 1472  # a robot over UDP
    assert session_batch_size(["tcp/10.0.0.1:7447"]) is None  # over TCP: Zenoh's batch
    assert session_batch_size(["tcp/10.0.0.1:7447", "udp/10.0.0.1:7447"]) == 1472
    # a router: its UDP clients shrink their own links; its TCP ones keep full batches
    assert session_batch_size([], ["tcp/0.0.0.0:7447", "udp/0.0.0.0:7447"]) is None
    assert session_batch_size([], ["udp/0.0.0.0:7447"]) == 1472
    assert session_batch_size(["tcp/10.0.0.2:7447"], ["udp/0.0.0.0:7447"]) is None  # a mesh
    assert session_batch_size([], []) is None


def test_a_fragment_resent_on_the_writers_key_fits_one_datagram() -> None:
    for key in ("perf/topic", "arpz/fleet/robot/robot12/sensor/camera_front", "k/" * 200):
        size = datagram_fragment_bytes(key)
        resend_key = wire.directed_key(key, "0" * 16)
        on_wire = size + wire.RESEND_FRAG.size + len(resend_key) + ZENOH_MESSAGE_OVERHEAD
        assert size == MIN_FRAGMENT_BYTES or on_wire <= UDP_BATCH_BYTES
        assert MIN_FRAGMENT_BYTES <= size <= DEFAULT_FRAGMENT_BYTES
    assert datagram_fragment_bytes("perf/topic") == DEFAULT_FRAGMENT_BYTES
    assert writer_fragment_bytes("k/" * 200, None) < DEFAULT_FRAGMENT_BYTES  # long key: less
    assert writer_fragment_bytes("k/" * 200, STREAM_FRAGMENT_BYTES) == STREAM_FRAGMENT_BYTES


# ----------------------------------------------------------------------- pure machines, bus
def pair(
    qos: QosProfile, link: Link | None = None, seed: int = 1, **reader_kw: int
) -> tuple[LossyBus, Node, Node]:
    bus = LossyBus(random.Random(seed), link or Link(), FakeClock())
    writer = bus.add(WriterMachine("t/a", qos, new_guid(), bus.clock, fragment_bytes=FRAG))
    reader = bus.add(ReaderMachine("t/*", qos, new_guid(), bus.clock, **reader_kw))
    bus.run_for(0.3)
    return bus, writer, reader


def machines(writer: Node, reader: Node) -> tuple[WriterMachine, ReaderMachine]:
    w, r = writer.machine, reader.machine
    assert isinstance(w, WriterMachine) and isinstance(r, ReaderMachine)
    return w, r


def reconciled(writer: Node, reader: Node) -> tuple[int, int, int, int, int]:
    """The reader's account of the writer; sent == delivered + lost + expired, per sample."""
    w, r = machines(writer, reader)
    first, last, delivered, lost, expired = r.accounted()[w.hex]
    assert last - first + 1 == delivered + lost + expired
    assert last == w.last_seq
    assert r.stats().in_assembly == 0 and r.stats().assembly_bytes == 0
    return first, last, delivered, lost, expired


def fragment_of(seq: int, index: int, *, resends: bool = True) -> Callable[[Send], bool]:
    """A drop rule: fragment ``index`` of sample ``seq`` (first sending, and resends too)."""

    def drop(msg: Send) -> bool:
        if msg.attachment is None:
            return False
        h = wire.decode_frag(msg.attachment)
        if h is None or (h.seq, h.fragment) != (seq, index):
            return False
        return resends or not h.flags & wire.F_RETRANSMIT

    return drop


def test_a_large_sample_is_one_seq_delivered_whole_small_ones_are_not_cut() -> None:
    bus, writer, reader = pair(QosProfile(depth=10))
    big, small = payload_of(1, 1000), b"x" * FRAG
    for payload in (small, big, small):
        bus.write(writer, payload)
        bus.run_for(0.01)
    bus.run_for(0.2)
    assert [p for p, _ in reader.delivered] == [small, big, small]
    assert [i.seq for _, i in reader.delivered] == [1, 2, 3]
    w, r = machines(writer, reader)
    ws, rs = w.stats(), r.stats()
    assert (ws.sent, ws.fragmented, ws.fragments_sent, ws.retransmitted) == (3, 1, 10, 0)
    assert (rs.delivered, rs.lost, rs.fragments_received, rs.nacks) == (3, 0, 10, 0)
    assert reconciled(writer, reader) == (1, 3, 3, 0, 0)


def test_one_lost_fragment_is_the_only_one_resent() -> None:
    bus, writer, reader = pair(QosProfile(depth=10))
    bus.drop = fragment_of(1, 4, resends=False)
    big = payload_of(2, 1000)
    bus.write(writer, big)
    bus.run_for(0.3)
    assert [p for p, _ in reader.delivered] == [big]
    w, r = machines(writer, reader)
    ws, rs = w.stats(), r.stats()
    assert (ws.retransmitted, ws.fragments_retransmitted, ws.fragments_nacked) == (1, 1, 1)
    assert (rs.fragments_nacked, rs.fragments_received, rs.lost) == (1, 10, 0)
    assert reader.delivered[0][1].retransmitted  # completed by a resend
    assert reconciled(writer, reader) == (1, 1, 1, 0, 0)


def test_a_lost_tail_fragment_is_asked_for_after_the_next_heartbeat() -> None:
    """The last sample of a stream, its last fragment lost: only the heartbeat tells the reader
    that the writer sent it all; nothing else is resent."""
    bus, writer, reader = pair(QosProfile(depth=10))
    bus.drop = fragment_of(1, 9, resends=False)
    bus.write(writer, payload_of(3, 1000))
    bus.run_for(1.0)
    w, _ = machines(writer, reader)
    assert len(reader.delivered) == 1 and w.stats().fragments_retransmitted == 1
    assert reconciled(writer, reader) == (1, 1, 1, 0, 0)


def test_a_sample_whose_fragments_never_complete_is_lost_once() -> None:
    """KEEP_LAST 5: fragment 3 of sample 2 never gets through; the samples behind it wait the
    reorder timeout, then sample 2 is counted lost ONCE (not per fragment) and the rest go on."""
    qos = QosProfile(depth=5, reorder_timeout_s=0.1)
    bus, writer, reader = pair(qos)
    bus.drop = fragment_of(2, 3)
    for i in range(4):
        bus.write(writer, payload_of(i, 1000))
        bus.run_for(0.005)
    bus.run_for(0.5)
    assert [i.seq for _, i in reader.delivered] == [1, 3, 4]
    _, r = machines(writer, reader)
    lost = sum(s.total_count_change for e, s in reader.events if e == "message_lost")  # type: ignore[attr-defined]
    assert r.stats().lost == lost == 1
    assert reconciled(writer, reader) == (1, 4, 3, 1, 0)


def test_an_overwritten_incomplete_sample_is_gapped_and_lost_once() -> None:
    """KEEP_LAST 1: the writer overwrote the sample before its missing fragment came; the
    reader's ACKNACK_FRAG is answered by a GAP: one loss on both sides."""
    bus, writer, reader = pair(QosProfile(depth=1, reorder_timeout_s=5.0))
    bus.drop = fragment_of(1, 0)
    bus.write(writer, payload_of(1, 1000))
    bus.write(writer, payload_of(2, 1000))
    bus.run_for(0.5)
    assert [i.seq for _, i in reader.delivered] == [2]
    w, r = machines(writer, reader)
    assert r.stats().lost == 1
    assert reconciled(writer, reader) == (1, 2, 1, 1, 0)
    assert w.stats().fragments_retransmitted == 0


def test_a_sample_beyond_max_sample_bytes_is_refused_and_lost_once() -> None:
    bus, writer, reader = pair(QosProfile(depth=10), max_sample_bytes=500)
    bus.write(writer, payload_of(1, 1000))
    bus.write(writer, b"small")
    bus.run_for(0.5)
    assert [p for p, _ in reader.delivered] == [b"small"]
    _, r = machines(writer, reader)
    rs = r.stats()
    assert (rs.samples_too_large, rs.lost, rs.delivered) == (1, 1, 1)
    assert rs.fragments_refused == rs.fragments_received - rs.fragments_duplicate
    assert reconciled(writer, reader) == (1, 2, 1, 1, 0)


def test_assembly_memory_is_bounded_and_everything_still_arrives() -> None:
    """Room for one sample in assembly: the fragments of the next ones are refused while it is
    incomplete, and asked for again once there is room. KEEP_ALL: every sample arrives."""
    qos = QosProfile(history=HistoryPolicy.KEEP_ALL, max_samples=10, reorder_timeout_s=60.0)
    bus, writer, reader = pair(qos, max_assembly_bytes=1500)
    bus.drop = fragment_of(1, 2, resends=False)
    payloads = [payload_of(i, 1000) for i in range(4)]
    for p in payloads:
        bus.write(writer, p)
    peak = 0
    for _ in range(1000):
        bus.step()
        peak = max(peak, machines(writer, reader)[1].stats().assembly_bytes)
    assert peak <= 1500
    assert [p for p, _ in reader.delivered] == payloads
    assert machines(writer, reader)[1].stats().fragments_refused > 0
    assert reconciled(writer, reader) == (1, 4, 4, 0, 0)


@pytest.mark.parametrize("seed", [2, 5, 29])
def test_a_late_joiner_gets_a_transient_local_history_of_large_samples_whole(seed: int) -> None:
    """The history is resent whole sample by sample, each as fragments; a lossy link loses some
    of them, those are asked for again one by one. A resent sample whose last fragment is lost
    is known complete from the SYNC heartbeat that came before any of it (seeds 5 and 29 lost
    the last sample to the reorder timeout when only a later heartbeat could tell)."""
    qos = QosProfile(durability=DurabilityPolicy.TRANSIENT_LOCAL, depth=3)
    bus = LossyBus(random.Random(seed), Link(loss=0.1, jitter_s=0.003), FakeClock())
    writer = bus.add(WriterMachine("t/a", qos, new_guid(), bus.clock, fragment_bytes=FRAG))
    payloads = [payload_of(i, 2500) for i in range(4)]
    for p in payloads:
        bus.write(writer, p)
    bus.run_for(0.1)
    reader = bus.add(ReaderMachine("t/*", qos, new_guid(), bus.clock))
    bus.run_for(2.0)
    assert [p for p, _ in reader.delivered] == payloads[1:]  # the 3 the history holds
    w, _ = machines(writer, reader)
    assert w.stats().fragments_retransmitted >= 3 * 25
    assert reconciled(writer, reader) == (2, 4, 3, 0, 0)


FAST = settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
qos_choices = st.sampled_from(
    [
        QosProfile(history=HistoryPolicy.KEEP_ALL, max_samples=20, reorder_timeout_s=60.0),
        QosProfile(depth=3, reorder_timeout_s=0.05),
        QosProfile(depth=1),
        QosProfile(reliability=ReliabilityPolicy.BEST_EFFORT, depth=5),
        QosProfile(depth=8, batch_max_samples=8, batch_max_delay_s=0.003),
        QosProfile(durability=DurabilityPolicy.TRANSIENT_LOCAL, depth=10),
    ]
)


@FAST
@given(
    seed=st.integers(0, 2**32),
    loss=st.sampled_from([0.0, 0.05, 0.2]),
    duplicate=st.sampled_from([0.0, 0.1]),
    jitter_s=st.sampled_from([0.0, 0.003]),
    qos=qos_choices,
    sizes=st.lists(st.sampled_from([10, FRAG, FRAG + 1, 1000, 2500]), min_size=1, max_size=25),
)
def test_every_sample_is_delivered_whole_once_or_lost_once(
    seed: int, loss: float, duplicate: float, jitter_s: float, qos: QosProfile, sizes: list[int]
) -> None:
    link = Link(loss=loss, duplicate=duplicate, delay_s=0.001, jitter_s=jitter_s)
    bus, writer, reader = pair(qos, link, seed)
    w, r = machines(writer, reader)
    payloads = [payload_of(seed + i, size) for i, size in enumerate(sizes)]
    for p in payloads:
        waited = 0
        while not w.has_room():
            bus.step()
            waited += 1
            assert waited < 100_000, "KEEP_ALL writer never got room"
        bus.write(writer, p)
        bus.run_for(0.002)
    bus.run_for(3.0)
    seqs = [info.seq for _, info in reader.delivered]
    assert seqs == sorted(set(seqs)), "delivered out of order or twice"
    for p, info in reader.delivered:
        assert p == payloads[info.seq - 1], "a sample delivered other than whole"
    first, last, delivered, lost, _ = reconciled(writer, reader)
    assert (first, last, delivered) == (1, len(sizes), len(seqs))
    lost_events = sum(s.total_count_change for e, s in reader.events if e == "message_lost")  # type: ignore[attr-defined]
    assert lost_events == lost == r.stats().lost
    if qos.history is HistoryPolicy.KEEP_ALL:
        assert seqs == list(range(1, len(sizes) + 1))


# ------------------------------------------------------------------ Writer/Reader, threads
class Collect(Sink):
    """test_large's sink, of samples: ``frames`` holds (payload, DataInfo)."""

    def __call__(self, payload: bytes, info: DataInfo) -> None:  # type: ignore[override]
        with self.lock:
            self.frames.append((payload, info))  # type: ignore[arg-type]


def test_writer_fragments_by_its_transports_link_and_the_reader_reassembles() -> None:
    class StreamTransport(MemoryTransport):
        fragment_bytes = STREAM_FRAGMENT_BYTES

    bus = MemoryBus()
    udp, tcp = MemoryTransport(bus), StreamTransport(bus)
    qos = QosProfile(history=HistoryPolicy.KEEP_ALL, max_samples=50)
    sink = Collect()
    payloads = [payload_of(i, 200_000) for i in range(3)]
    with (
        closing(udp),
        closing(tcp),
        Reader(udp, "cam/*", qos, sink) as reader,
        Writer(udp, "cam/udp", qos) as w_udp,
        Writer(tcp, "cam/tcp", qos) as w_tcp,
    ):
        assert w_udp.fragment_bytes == DEFAULT_FRAGMENT_BYTES  # no property: safe for UDP
        assert w_tcp.fragment_bytes == STREAM_FRAGMENT_BYTES
        wait_until(
            lambda: reader.matched_count == 2 and w_udp.matched_count == w_tcp.matched_count == 1,
            what="match",
        )
        for p in payloads:
            w_udp.write(p)
            w_tcp.write(p)
        wait_until(lambda: len(sink) == 6, what="every sample")
        for key in ("cam/udp", "cam/tcp"):
            assert [p for p, i in sink.frames if i.key == key] == payloads
        assert w_udp.stats().fragments_sent == 3 * 157 and w_tcp.stats().fragments_sent == 3 * 4
        assert reader.stats().delivered == 6 and reader.stats().lost == 0


@pytest.mark.parametrize("loss", [0.1])
def test_large_samples_arrive_over_a_lossy_transport(loss: float) -> None:
    bus = MemoryBus()
    lossy, clean = LossyTransport(bus, loss, seed=4), MemoryTransport(bus)
    qos = QosProfile(history=HistoryPolicy.KEEP_ALL, max_samples=20)
    sink = Collect()
    payloads = [payload_of(i, 64_000) for i in range(5)] + [b"small"]
    with (
        closing(lossy),
        closing(clean),
        Reader(clean, "t/a", qos, sink) as reader,
        Writer(lossy, "t/a", qos) as writer,
    ):
        wait_until(
            lambda: writer.matched_count == 1 and writer.wait_for_acknowledgments(0.01),
            what="match",
        )
        for p in payloads:
            writer.write(p)
        wait_until(lambda: len(sink) == len(payloads), timeout_s=20, what="every sample")
        assert [p for p, _ in sink.frames] == payloads
        assert writer.wait_for_acknowledgments(5.0)
        ws, rs = writer.stats(), reader.stats()
        assert ws.sent == rs.delivered == len(payloads) and rs.lost == 0
        assert ws.fragmented == 5 and lossy.dropped > 0
        # the resends were fragments, not whole samples: far fewer than one sample's worth
        assert 0 < ws.fragments_retransmitted < 5 * 50


def test_an_outlet_and_an_inlet_carry_a_large_message_whole_and_count_it_once() -> None:
    bus = MemoryBus()
    a, b = LossyTransport(bus, 0.05, seed=9), MemoryTransport(bus)
    got: list[tuple[str, bytes]] = []
    qos = QosProfile(depth=10)
    big = payload_of(7, 300_000)
    with closing(a), closing(b):
        inlet = Inlet(b, "k/*", qos, lambda key, payload: got.append((key, payload)))
        outlet = Outlet(a, "k/x", qos)
        try:
            wait_until(lambda: outlet.matched, what="match")
            assert outlet.send(big, 1) and outlet.send(b"small", 2)
            wait_until(lambda: len(got) == 2, timeout_s=10, what="both messages")
            assert got == [("k/x", big), ("k/x", b"small")]
            stats = inlet.stats()
            assert stats is not None and (stats.delivered, stats.lost) == (2, 0)
            assert stats.fragments_received >= 235  # 300 000 B in 1280-byte fragments
        finally:
            outlet.close()
            inlet.close()


def test_a_large_sample_written_inside_a_robots_tick_leaves_in_order_with_the_bundle() -> None:
    """A robot's sensor writers put through a Bundler inside the tick: what the tick holds
    leaves before the fragments (older seqs first), and the fragments leave at once."""
    bus = MemoryBus()
    robot, server = MemoryTransport(bus), MemoryTransport(bus)
    bundler = Bundler(robot, max_bytes=DEFAULT_FRAGMENT_BYTES)
    sink = Collect()
    qos = QosProfile(depth=10)
    big = payload_of(8, 20_000)
    with (
        closing(robot),
        closing(server),
        Reader(server, "f/robot/r1/sensor/*", qos, sink) as reader,
        Writer(bundler, "f/robot/r1/sensor/a", qos, block=False) as a,
        Writer(bundler, "f/robot/r1/sensor/b", qos, block=False) as b,
    ):
        wait_until(
            lambda: reader.matched_count == 2 and a.matched_count == b.matched_count == 1,
            what="match",
        )
        with bundler.collect():
            a.write(b"small 1")
            b.write(big)
            a.write(b"small 2")
        wait_until(lambda: len(sink) == 3, what="all three")
        assert [(i.key, p) for p, i in sink.frames] == [
            ("f/robot/r1/sensor/a", b"small 1"),
            ("f/robot/r1/sensor/b", big),
            ("f/robot/r1/sensor/a", b"small 2"),
        ]
        assert reader.stats().lost == 0 and b.stats().fragmented == 1
