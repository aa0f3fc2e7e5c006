from __future__ import annotations

from collections.abc import Callable

from hypothesis import given
from hypothesis import strategies as st

from arpz.core.protocol import wire
from arpz.core.protocol._common import BadInput, new_guid
from arpz.core.protocol.actions import Action, Notify
from arpz.core.protocol.qos import QosProfile
from arpz.core.protocol.reader_machine import ReaderMachine
from arpz.core.protocol.timers import FakeClock
from arpz.core.protocol.writer_machine import RESEND_BUDGET, WriterMachine

G1, G2 = b"\x01" * 8, b"\x02" * 8


def test_roundtrips_and_sizes() -> None:
    """Every message kind of the protocol: DATA, resend, batch, HEARTBEAT, ACKNACK, GAP."""
    att = wire.encode_data(wire.F_RETRANSMIT, G1, 5, -3)
    assert len(att) == 26 and wire.decode_data(att) == (wire.F_RETRANSMIT, G1, 5, -3, -1)
    resend = wire.encode_resend(G1, 5, -3, 2**32 + 7)  # the echoed count wraps as the ACKNACK's
    assert len(resend) == 30 and wire.decode_data(resend) == (wire.F_RETRANSMIT, G1, 5, -3, 7)
    not_a_resend = wire.RESEND.pack(wire.VERSION, 0, G1, 5, -3, 7)
    assert wire.decode_data(not_a_resend) is None
    # a batch of samples of one size (the decoder's fast path) and one of mixed sizes
    for payloads in ([b"ab", b"cd", b"ef"], [b"a", b"", b"cde"]):
        payload, att = wire.encode_batch(wire.F_ACK_REQUEST, G1, 7, payloads, [10, 20, -30])
        assert payload == b"".join(payloads) and len(att) == 20 + 3 * 12
        flags = wire.F_ACK_REQUEST | wire.F_BATCH
        assert wire.decode_batch(payload, att) == (flags, G1, 7, (10, 20, -30), payloads)
    hb = wire.encode_heartbeat(wire.HB_FINAL, G1, 3, 9, 7)
    assert len(hb) == 31 and wire.decode_heartbeat(hb) == (wire.HB_FINAL, G1, 3, 9, 7)
    assert wire.control_kind(hb) == wire.KIND_HEARTBEAT
    an = wire.encode_acknack(G2, G1, 4, 1, [(5, 6), (9, 9)])
    assert len(an) == 32 + 32 and wire.decode_acknack(an) == (G2, G1, 4, 1, [(5, 6), (9, 9)], ())
    assert wire.control_kind(an) == wire.KIND_ACKNACK
    gap = wire.encode_gap(G1, G2, [(1, 3)])
    assert len(gap) == 20 + 16 and wire.decode_gap(gap) == (G1, G2, [(1, 3)])
    assert wire.control_kind(gap) == wire.KIND_GAP
    assert wire.to_ranges([1, 2, 3, 7, 9, 10]) == [(1, 3), (7, 7), (9, 10)]


def decoded_again(data: bytes) -> dict[str, bytes]:
    """What each wire decoder made of ``data``, encoded again (decoders that returned None
    left out). Whatever decodes must be exactly what the bytes say: encoded again it gives
    ``data`` back, so no decoder fills in, truncates or ignores a field of a malformed message."""
    out: dict[str, bytes] = {}
    if (hb := wire.decode_heartbeat(data)) is not None:
        out["heartbeat"] = wire.encode_heartbeat(*hb)
    if (an := wire.decode_acknack(data)) is not None:
        out["acknack"] = wire.encode_acknack(*an)
    if (gap := wire.decode_gap(data)) is not None:
        out["gap"] = wire.encode_gap(*gap)
    if (h := wire.decode_data(data)) is not None:
        out["data"] = (
            wire.DATA.pack(wire.VERSION, h.flags, h.writer, h.seq, h.stamp_ns)
            if h.echo == -1
            else wire.RESEND.pack(wire.VERSION, h.flags, h.writer, h.seq, h.stamp_ns, h.echo)
        )
    if len(data) in (wire.DATA_FRAG.size, wire.RESEND_FRAG.size):
        f = wire.decode_frag(data)
        if f is not None:
            head = (wire.VERSION, f.flags, f.writer, f.seq, f.stamp_ns, f.fragment, f.total)
            out["fragment"] = (
                wire.DATA_FRAG.pack(*head, f.chunk)
                if f.echo == -1
                else wire.RESEND_FRAG.pack(*head, f.chunk, f.echo)
            )
    return out


def test_key_shapes_stay_below_the_topic() -> None:
    assert wire.split_control_key("a/b/rel/an/w/r", "an", 2) == ("a/b", ["w", "r"])
    assert wire.split_control_key("a/b/rel/hb/w", "an", 1) is None
    assert wire.split_control_key("rel/hb/w", "hb", 1) is None


# each message's layout with every field drawn over its whole width (versions and kinds near
# the valid ones, range counts that may not match): where a missing check would let garbage by
_u8, _u32, _u64 = st.integers(0, 2**8 - 1), st.integers(0, 2**32 - 1), st.integers(0, 2**64 - 1)
_version, _kind = st.integers(0, 2), st.integers(0, 4)
_guid = st.binary(min_size=8, max_size=8)


@st.composite
def _ranged(draw: st.DrawFn, head: Callable[[int], bytes]) -> bytes:
    ranges = draw(st.lists(st.tuples(_u64, _u64), max_size=4))
    n = len(ranges) + draw(st.sampled_from([0, 0, 0, -1, 1]))
    return head(max(n, 0)) + b"".join(wire.RANGE.pack(lo, hi) for lo, hi in ranges)


@st.composite
def _frag_ranged(draw: st.DrawFn, head: Callable[[int], bytes]) -> bytes:
    """An ACKNACK_FRAG's shape: ACKNACK ranges, then fragment ranges with a count that may lie."""
    frags = draw(st.lists(st.tuples(_u64, _u32, _u32), max_size=4))
    m = len(frags) + draw(st.sampled_from([0, 0, 0, -1, 1]))
    tail = wire.FRAG_COUNT.pack(max(m, 0)) + b"".join(wire.FRAG_RANGE.pack(*f) for f in frags)
    return draw(_ranged(head)) + tail


#: DATA_FRAG's fields: the DATA header's, then fragment index, total and chunk
_FRAG_FIELDS = (_version, _u8, _guid, _u64, st.integers(-(2**63), 2**63 - 1), _u32, _u32, _u32)

_SHAPED = st.one_of(
    st.binary(max_size=200),
    st.builds(wire.HEARTBEAT.pack, _version, _kind, _u8, _guid, _u64, _u64, _u32),
    st.builds(wire.DATA.pack, _version, _u8, _guid, _u64, st.integers(-(2**63), 2**63 - 1)),
    st.builds(wire.RESEND.pack, _version, _u8, _guid, _u64, st.integers(-(2**63), 2**63 - 1), _u32),
    st.tuples(_version, _kind, _guid, _guid, _u64, _u32).flatmap(
        lambda f: _ranged(lambda n: wire.ACKNACK.pack(*f, n))
    ),
    st.tuples(_version, _kind, _guid, _guid).flatmap(
        lambda f: _ranged(lambda n: wire.GAP.pack(*f, n))
    ),
    st.tuples(_version, _kind, _guid, _guid, _u64, _u32).flatmap(
        lambda f: _frag_ranged(lambda n: wire.ACKNACK.pack(*f, n))
    ),
    st.builds(wire.DATA_FRAG.pack, *_FRAG_FIELDS),
    st.builds(wire.RESEND_FRAG.pack, *_FRAG_FIELDS, _u32),
)


@given(_SHAPED)
def test_random_bytes_never_decode_to_garbage_or_raise(data: bytes) -> None:
    for kind, again in decoded_again(data).items():
        assert again == data, kind


@given(st.binary(max_size=120), st.one_of(st.none(), st.binary(max_size=40)))
def test_machines_count_and_ignore_any_input(payload: bytes, attachment: bytes | None) -> None:
    """Nothing matched, so every input is foreign: each is counted as bad input and acted on
    no further (the one answer allowed is INCOMPATIBLE_QOS for a sample without a header)."""
    clock = FakeClock()
    w = WriterMachine("t/a", QosProfile(), new_guid(), clock)
    r = ReaderMachine("t/*", QosProfile(), new_guid(), clock)
    token = payload.decode("latin-1")
    calls: list[tuple[BadInput, Callable[[], list[Action]]]] = [
        (w.bad, lambda: w.on_acknack("t/a/rel/an/x/y", payload, attachment)),
        (r.bad, lambda: r.on_heartbeat("t/a/rel/hb/x", payload, attachment)),
        (r.bad, lambda: r.on_directed("t/a/rel/rx/y", payload, attachment)),
        (w.bad, lambda: w.on_reader_token(token, True)),
        (r.bad, lambda: r.on_writer_token(token, True)),
    ]
    for bad, call in calls:
        before = bad.total()
        assert call() == []
        assert bad.total() > before
    before = r.bad.total()
    actions = r.on_data("t/a", payload, attachment)
    assert r.bad.total() > before
    if attachment is None:
        assert [type(a) for a in actions] == [Notify] and actions[0].event == "incompatible_qos"
    else:
        assert actions == []
    assert r.stats().delivered == 0


def test_forged_acknack_with_huge_ranges_costs_bounded_work() -> None:
    clock = FakeClock()
    w = WriterMachine("t/a", QosProfile(depth=1000), new_guid(), clock)
    reader = new_guid()
    w.on_reader_token(wire.reader_token("t/a", reader.hex(), "RVA_0_0"), True)
    for i in range(1000):
        w.write(b"%d" % i)
    huge = [(1 + i * 1000, (i + 1) * 1000 + 10**15) for i in range(wire.MAX_RANGES)]
    key = wire.acknack_key("t/a", w.hex, reader.hex())
    actions = w.on_acknack(key, wire.encode_acknack(reader, w.guid, 1, 1, huge), None)
    assert len(actions) <= RESEND_BUDGET + 1
    stranger = new_guid()
    stranger_key = wire.acknack_key("t/a", w.hex, stranger.hex())
    assert w.on_acknack(stranger_key, wire.encode_acknack(stranger, w.guid, 1, 1, huge), None) == []
    assert w.bad.counts["ACKNACK from an unmatched reader"] == 1
    # the matched reader's guid on another reader's key is refused, not taken as its ACKNACK
    assert w.on_acknack(stranger_key, wire.encode_acknack(reader, w.guid, 1, 1, huge), None) == []
    assert w.bad.counts["ACKNACK with another guid than its key's reader"] == 1
