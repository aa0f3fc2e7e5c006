"""Fuzzing every decoder of untrusted bytes: only the documented errors may escape.

Anything on a Zenoh key can be put there by a buggy or hostile client, so each decoder in
``arpz.core.messages`` (found by introspection, so a decoder added later is fuzzed too) must either
return a typed message or raise one of ``arpz.core.messages.DECODE_ERRORS``; the reliable channel's
wire decoders must return ``None`` for anything they cannot use. The CEDDP's ingest, which is
where those bytes land, must count every payload in exactly one place and never raise.
"""

from __future__ import annotations

import math
import struct
from typing import Any

import msgspec
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from arpz.ceddp.cache_control import CacheControl
from arpz.ceddp.ingest import Ingest
from arpz.ceddp.planner import HelloRelay
from arpz.core import keys, messages
from arpz.core.messages import DECODE_ERRORS, Hello, Sample, encode
from arpz.core.protocol import wire
from tests.unit.reliability.test_wire import decoded_again

DECODERS: dict[str, msgspec.msgpack.Decoder[Any]] = {
    name: value
    for name, value in vars(messages).items()
    if isinstance(value, msgspec.msgpack.Decoder)
}
FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])

# msgpack-encodable values of every shape: what a client that uses the right format with the
# wrong content sends
scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**63), max_value=2**64 - 1),
    st.floats(),
    st.text(max_size=20),
    st.binary(max_size=20),
)
structures = st.recursive(
    scalars,
    lambda inner: st.one_of(
        st.lists(inner, max_size=8),
        st.dictionaries(
            st.one_of(st.text(max_size=10), st.integers(-(2**63), 2**63)), inner, max_size=6
        ),
    ),
    max_leaves=30,
)


def _valid_payloads() -> list[bytes]:
    """One well-formed payload of each wire type, for the mutation strategy."""
    return [
        encode(Sample("robot1:0123456789ab", 1, 1_763_900_000_000_000_000, 1.5)),
        encode(Sample("robot1:0123456789ab", 2, 1, "detect")),
        encode(Hello("robot1:0123456789ab", 3, 4, "robot1", 5, 6, 0)),
        encode(messages.Command("ceddp:0123456789ab", 1, 2, [0.5, -0.1])),
        encode(
            messages.RobotStats(
                "robot1", "0123456789ab", 1, False, {"pir": messages.TopicCounters(1, 1)}
            )
        ),
        encode(
            messages.Announce(
                "robot1",
                "0123456789ab",
                [messages.TopicInfo("pir", "pir", 10.0, "str")],
                ["velocity"],
            )
        ),
    ]


@st.composite
def mutated(draw: st.DrawFn) -> bytes:
    """A valid payload with bytes flipped, cut, inserted, or a string made invalid UTF-8."""
    data = bytearray(draw(st.sampled_from(_valid_payloads())))
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["flip", "cut", "insert", "utf8"]))
        at = draw(st.integers(0, max(len(data) - 1, 0)))
        if op == "flip" and data:
            data[at] ^= draw(st.integers(1, 255))
        elif op == "cut":
            del data[at:]
        elif op == "insert":
            data[at:at] = draw(st.binary(min_size=1, max_size=8))
        else:  # a fixstr header followed by bytes that are not UTF-8
            data[at:at] = b"\xa3\xff\xfe\xfd"
    return bytes(data)


def _encode_any(value: Any) -> bytes:
    return msgspec.msgpack.encode(value)


untrusted = st.one_of(
    st.binary(max_size=256),
    mutated(),
    structures.map(_encode_any),
    st.lists(structures, min_size=3, max_size=9).map(_encode_any),  # array-like, wrong fields
)


def _decode(decoder: msgspec.msgpack.Decoder[Any], payload: bytes) -> Any:
    try:
        return decoder.decode(payload)
    except DECODE_ERRORS:
        return None


@FUZZ
@given(payload=untrusted)
@example(payload=b"")
@example(payload=b"\xdd\xff\xff\xff\xff")  # an array header claiming 4 billion elements
@example(payload=b"\x91" * 5000 + b"\xc0")  # deeply nested arrays
@example(payload=b"\x94\xa3\xff\xfe\xfd\x01\x02\xc3")  # a Sample whose writer is not UTF-8
def test_every_message_decoder_raises_only_decode_errors(payload: bytes) -> None:
    assert len(DECODERS) >= 9, sorted(DECODERS)
    for decoder in DECODERS.values():
        message = _decode(decoder, payload)
        if message is not None:
            # what decoded must encode again (nothing half-built reaches the rest of arpz)
            again = decoder.decode(encode(message))
            assert type(again) is type(message)


@FUZZ
@given(payload=st.one_of(st.binary(max_size=600), mutated()))
def test_reliable_channel_wire_decoders_return_none_for_bad_input(payload: bytes) -> None:
    # a decoder that does not return None must have read a well-formed message: encoded again,
    # it is the input itself
    for kind, again in decoded_again(payload).items():
        assert again == payload, kind
    kind = wire.control_kind(payload)
    assert kind is None or (payload[0] == wire.VERSION and kind == payload[1])


@st.composite
def batches(draw: st.DrawFn) -> tuple[bytes, bytes, wire.Batch | None]:
    """(payload, attachment, what it must decode to): a batch as a writer encodes it, or one
    whose lengths were made not to add up (None: it must be refused)."""
    n = draw(st.integers(1, 40))
    if draw(st.booleans()):  # one size for all (the decoder's fast path)
        size = draw(st.integers(0, 8))
        payloads = draw(st.lists(st.binary(min_size=size, max_size=size), min_size=n, max_size=n))
    else:
        payloads = draw(st.lists(st.binary(max_size=20), min_size=n, max_size=n))
    stamps = draw(st.lists(st.integers(-(2**63), 2**63 - 1), min_size=n, max_size=n))
    first = draw(st.integers(1, wire.MAX_SEQ - n + 1))
    writer = draw(st.binary(min_size=8, max_size=8))
    payload, attachment = wire.encode_batch(0, writer, first, payloads, stamps)
    expected: wire.Batch | None = wire.Batch(wire.F_BATCH, writer, first, tuple(stamps), payloads)
    tamper = draw(st.sampled_from(["none", "longer", "shorter", "length"]))
    if tamper == "longer" or (tamper == "shorter" and not payload):
        payload += draw(st.binary(min_size=1, max_size=4))
        expected = None
    elif tamper == "shorter":
        payload = payload[: draw(st.integers(0, len(payload) - 1))]
        expected = None
    elif tamper == "length":  # one sample's length one more than it is
        at = wire.BATCH.size + 8 * n + 4 * draw(st.integers(0, n - 1))
        (length,) = struct.unpack_from("!I", attachment, at)
        attachment = attachment[:at] + struct.pack("!I", length + 1) + attachment[at + 4 :]
        expected = None
    return payload, attachment, expected


@FUZZ
@given(batch=batches())
def test_the_batch_decoder_accepts_only_batches_whose_lengths_add_up(
    batch: tuple[bytes, bytes, wire.Batch | None],
) -> None:
    payload, attachment, expected = batch
    assert wire.decode_batch(payload, attachment) == expected


@FUZZ
@given(payload=st.binary(max_size=300), attachment=st.binary(max_size=200))
def test_the_batch_decoder_refuses_random_bytes(payload: bytes, attachment: bytes) -> None:
    assert wire.decode_batch(payload, attachment) is None


class _KeySink:
    """Builds the command key as the server's sink does, so a bad name fails as it would."""

    def __init__(self) -> None:
        self.sent: list[str] = []

    def send(self, robot: str, name: str, payload: bytes) -> None:
        self.sent.append(keys.command_key("f", robot, name))


def _ingest(sink: _KeySink | None = None) -> Ingest:
    relay = HelloRelay(sink or _KeySink(), "ceddp:0123456789ab", relay="r2")
    relay.on_robot("r2", True)
    return Ingest("f", relay, CacheControl(enabled=True))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    topic=st.sampled_from(["pir", "lidar", "hello"]),
    payloads=st.lists(
        st.one_of(untrusted, st.sampled_from(_valid_payloads()[:2])), min_size=1, max_size=20
    ),
)
def test_ingest_counts_every_payload_once_and_never_raises(
    topic: str, payloads: list[bytes]
) -> None:
    ingest = _ingest()
    key = f"arpz/f/robot/r1/sensor/{topic}"
    for payload in payloads:
        ingest.handle_sensor(key, payload, 1_763_900_000_000_000_000)
    m = ingest.topics[("r1", topic)]
    assert m.received + m.decode_errors == len(payloads)
    cc = ingest.cache_counters("r1", topic)
    # cache control sees every sensor reading received and no Hello (they are probes)
    assert cc.hits + cc.misses == (0 if topic == "hello" else m.received)
    assert math.isfinite(m.lost) and m.lost >= 0


@pytest.mark.parametrize("origin", ["Robot1", "robot1/cmd", "*", ""])
def test_a_hello_with_an_invalid_origin_is_counted_not_raised(origin: str) -> None:
    sink = _KeySink()
    ingest = _ingest(sink)
    payload = encode(Hello("r1:0123456789ab", 1, 1, origin, 1, 1, 2))
    ingest.handle_sensor("arpz/f/robot/r1/sensor/hello", payload, 2)
    m = ingest.topics[("r1", "hello")]
    assert (m.received, m.decode_errors) == (1, 0)  # a well-formed Hello, received
    relay = ingest.planner
    assert isinstance(relay, HelloRelay)
    assert relay.counters.bad_origin == 1  # counted where the origin is checked
    assert sink.sent == []  # and dropped: no command key built from the bad origin
