from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from arpz.reliability import wire
from arpz.reliability._common import new_guid
from arpz.reliability.qos import QosProfile
from arpz.reliability.reader_machine import ReaderMachine
from arpz.reliability.timers import FakeClock
from arpz.reliability.writer_machine import RESEND_BUDGET, WriterMachine

G1, G2 = b"\x01" * 8, b"\x02" * 8


def test_roundtrips_and_sizes() -> None:
    att = wire.encode_data(wire.F_RETRANSMIT, G1, 5, -3)
    assert len(att) == 26 and wire.decode_data(att) == (wire.F_RETRANSMIT, G1, 5, -3)
    hb = wire.encode_heartbeat(wire.HB_FINAL, G1, 3, 9, 7)
    assert len(hb) == 31 and wire.decode_heartbeat(hb) == (wire.HB_FINAL, G1, 3, 9, 7)
    an = wire.encode_acknack(G2, G1, 4, 1, [(5, 6), (9, 9)])
    assert len(an) == 32 + 32 and wire.decode_acknack(an) == (G2, G1, 4, 1, [(5, 6), (9, 9)])
    gap = wire.encode_gap(G1, G2, [(1, 3)])
    assert wire.decode_gap(gap) == (G1, G2, [(1, 3)])
    assert wire.to_ranges([1, 2, 3, 7, 9, 10]) == [(1, 3), (7, 7), (9, 10)]


def test_key_shapes_stay_below_the_topic() -> None:
    assert wire.split_control_key("a/b/rel/an/w/r", "an", 2) == ("a/b", ["w", "r"])
    assert wire.split_control_key("a/b/rel/hb/w", "an", 1) is None
    assert wire.split_control_key("rel/hb/w", "hb", 1) is None


@given(st.binary(max_size=200))
def test_random_bytes_never_decode_to_garbage_or_raise(data: bytes) -> None:
    for decode in (wire.decode_heartbeat, wire.decode_acknack, wire.decode_gap):
        decode(data)
    wire.decode_data(data)


@given(st.binary(max_size=120), st.one_of(st.none(), st.binary(max_size=40)))
def test_machines_count_and_ignore_any_input(payload: bytes, attachment: bytes | None) -> None:
    clock = FakeClock()
    w = WriterMachine("t/a", QosProfile(), new_guid(), clock)
    r = ReaderMachine("t/*", QosProfile(), new_guid(), clock)
    w.on_acknack("t/a/rel/an/x/y", payload, attachment)
    r.on_data("t/a", payload, attachment)
    r.on_heartbeat("t/a/rel/hb/x", payload, attachment)
    r.on_directed("t/a/rel/rx/y", payload, attachment)
    w.on_reader_token(payload.decode("latin-1"), True)
    r.on_writer_token(payload.decode("latin-1"), True)
    assert r.stats().delivered == 0


def test_forged_acknack_with_huge_ranges_costs_bounded_work() -> None:
    clock = FakeClock()
    w = WriterMachine("t/a", QosProfile(depth=1000), new_guid(), clock)
    reader = new_guid()
    w.on_reader_token(wire.reader_token("t/a", reader.hex(), "RVA_0_0"), True)
    for i in range(1000):
        w.write(b"%d" % i)
    huge = [(1 + i * 1000, (i + 1) * 1000 + 10**15) for i in range(wire.MAX_RANGES)]
    actions = w.on_acknack("k", wire.encode_acknack(reader, w.guid, 1, 1, huge), None)
    assert len(actions) <= RESEND_BUDGET + 1
    assert w.on_acknack("k", wire.encode_acknack(new_guid(), w.guid, 1, 1, huge), None) == []
    assert w.bad.counts["ACKNACK from an unmatched reader"] == 1
