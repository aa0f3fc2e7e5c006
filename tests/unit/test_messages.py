import msgspec
from hypothesis import given
from hypothesis import strategies as st

from arpz.core.messages import (
    DECODE_ERRORS,
    HELLO_DECODER,
    SAMPLE_DECODER,
    STATS_DECODER,
    Hello,
    HelloStats,
    RobotStats,
    Sample,
    TopicCounters,
    encode,
)

ints = st.integers(min_value=0, max_value=2**63 - 1)
values = st.one_of(st.floats(allow_nan=False), st.booleans(), st.text(max_size=30))


@given(st.text(max_size=40), ints, ints, values)
def test_sample_round_trip_keeps_value_and_type(
    writer: str, seq: int, stamp: int, value: float | bool | str
) -> None:
    decoded = SAMPLE_DECODER.decode(encode(Sample(writer, seq, stamp, value)))
    assert decoded == Sample(writer, seq, stamp, value)
    assert type(decoded.value) is type(value)


@given(
    st.text(max_size=20),
    ints,
    ints,
    st.text(max_size=20),
    ints,
    ints,
    st.integers(min_value=0, max_value=3),
)
def test_hello_round_trip(
    writer: str, seq: int, stamp: int, origin: str, oseq: int, t0: int, stage: int
) -> None:
    hello = Hello(writer, seq, stamp, origin, oseq, t0, stage)
    assert HELLO_DECODER.decode(encode(hello)) == hello


def test_sample_is_a_plain_msgpack_array_as_docs_protocol_md_says() -> None:
    raw = msgspec.msgpack.decode(encode(Sample("robot1:abc", 7, 123, "detect", 100, 90)))
    assert raw == ["robot1:abc", 7, 123, "detect", 100, 90]
    # a client that writes the four first fields only is still understood
    old = SAMPLE_DECODER.decode(msgspec.msgpack.encode(["robot1:abc", 7, 123, "detect"]))
    assert old == Sample("robot1:abc", 7, 123, "detect", 0, 0)


@given(
    st.dictionaries(
        st.from_regex(r"[a-z]{1,8}", fullmatch=True),
        st.builds(TopicCounters, produced=ints, sent=ints, held_back=ints),
        max_size=5,
    ),
    st.booleans(),
)
def test_stats_round_trip(topics: dict[str, TopicCounters], final: bool) -> None:
    stats = RobotStats(
        robot="r1",
        incarnation="i",
        stamp_ns=5,
        final=final,
        topics=topics,
        hello=HelloStats(sent=3, received=2, lost=1, rtt_ms_p50=1.5),
    )
    assert STATS_DECODER.decode(encode(stats)) == stats


@given(st.binary(max_size=64))
def test_garbage_never_decodes_to_anything_but_a_decode_error(data: bytes) -> None:
    try:
        sample = SAMPLE_DECODER.decode(data)
    except DECODE_ERRORS:
        return
    assert isinstance(sample, Sample)
