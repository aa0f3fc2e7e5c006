"""arpz's own messages -> DiagnosticArray -> CDR -> arpz message is the identity, for every
message ``arpz record`` writes so (and the plain fields of the JSON form), and command values ->
standard ROS 2 types -> command values too (arpz/core/rosmsg/reports.py, commands.py)."""

from __future__ import annotations

import math

import msgspec
import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from arpz.core.messages import (
    Announce,
    ClockStats,
    Command,
    Hello,
    HelloStats,
    InboundCounters,
    LargeSample,
    QosAck,
    RobotStats,
    Sample,
    Telemetry,
    TopicCounters,
    TopicInfo,
)
from arpz.core.rosmsg.commands import (
    BOOL,
    FLOAT64,
    FLOAT64_ARRAY,
    STRING,
    TWIST,
    command_cdr,
    command_from_ros,
    command_to_ros,
    command_type,
)
from arpz.core.rosmsg.convert import ConversionError, deserialize
from arpz.core.rosmsg.reports import (
    DIAGNOSTIC_ARRAY,
    STALE,
    flatten,
    from_fields,
    message_from_cdr,
    report_cdr,
    report_from_cdr,
    report_to_ros,
    to_fields,
    unflatten,
)

STATS = RobotStats(
    robot="robot1",
    incarnation="abc",
    stamp_ns=1_796_000_000_123_456_789,
    final=True,
    topics={
        "lidar": TopicCounters(produced=10, sent=9, held_back=1, rate_hz=19.95),
        # a map key with every character the key/value form escapes
        "odd.name[0]{x}%": TopicCounters(),
    },
    hello=HelloStats(sent=3, rtt_ms_p50=1.25),
    qos_rate_hz=None,
    inbound={"cmd/velocity": InboundCounters(delivered=5, writers={"g1": [1, 5, 5, 0, 0]})},
    watchdog_stops={},
    watchdog_stopped=[],
    incompatible_qos=["cmd/velocity: DEADLINE"],
    clock=ClockStats(offset_ns=-120_000, delay_ns=None, samples=8),
    cpu_percent=math.inf,
)
ANNOUNCE = Announce(
    robot="robot1",
    incarnation="abc",
    sensors=[
        TopicInfo("lidar", "lidar", 20.0, "float", priority=2.0, max_rate_hz=None),
        TopicInfo("cam", "camera", 5.0, "bytes", configured_rate_hz=10.0),
    ],
    commands=[],
    mode="none",
)
MESSAGES: list[msgspec.Struct] = [
    STATS,
    ANNOUNCE,
    QosAck("robot1", "abc", "ceddp:1", 3, 12, "refused", "null", 15.5, 4, None),
    Telemetry("robot1:abc", 7, 12, 1.5, -0.0, 3.14159, True),
    Command("ceddp:1", 1, 5, [0.5, -0.25]),
    Hello("robot1:abc", 3, 5, "robot2", 1, 4, 2),
    Sample("robot1:abc", 1, 5, "detect"),
    LargeSample("robot1:abc", 1, 5, b"\x00\xff" * 10),
]


@pytest.mark.parametrize("message", MESSAGES, ids=lambda m: type(m).__name__)
def test_every_message_comes_back_from_its_fields_and_its_diagnostic_array(
    message: msgspec.Struct,
) -> None:
    assert from_fields(type(message), to_fields(message)) == message
    if isinstance(message, Hello | Command | Sample | LargeSample):
        # the JSON form of --include-internal (bytes as base64; JSON has no inf, which the
        # reports, written as DiagnosticArrays only, may hold)
        as_json = msgspec.json.decode(msgspec.json.encode(to_fields(message)))
        assert from_fields(type(message), as_json) == message
    data = report_cdr(message, name="robot1/x", hardware_id="robot1", summary="s", stamp_ns=7)
    assert message_from_cdr(type(message), data) == message


def test_the_diagnostic_array_is_readable_as_a_ros_user_expects() -> None:
    data = report_cdr(
        STATS, name="robot1/stats", hardware_id="robot1", summary="final", stamp_ns=STATS.stamp_ns
    )
    array = deserialize(data, DIAGNOSTIC_ARRAY)
    assert (array.header.stamp.sec, array.header.stamp.nanosec) == (1_796_000_000, 123_456_789)
    [status] = array.status
    assert (status.name, status.hardware_id, status.message, status.level) == (
        "robot1/stats",
        "robot1",
        "final",
        0,
    )
    values = {kv.key: kv.value for kv in status.values}
    assert values["topics.lidar.sent"] == "9"
    assert values["topics.lidar.rate_hz"] == "19.95"
    assert values["final"] == "true"
    assert values["qos_rate_hz"] == "null"
    assert values["cpu_percent"] == "inf"
    assert values["clock.offset_ns"] == "-120000"
    assert values["incompatible_qos[0]"] == "cmd/velocity: DEADLINE"
    assert values["inbound.cmd/velocity.writers.g1[4]"] == "0"
    assert values["watchdog_stops{}"] == values["watchdog_stopped[]"] == ""
    assert values["topics.odd%2Ename%5B0%5D%7Bx%7D%25.sent"] == "0"
    report = report_from_cdr(data)
    assert report.stamp_ns == STATS.stamp_ns and report.fields["topics"]["lidar"]["sent"] == "9"


def test_a_liveliness_report_is_stale_when_the_token_vanished() -> None:
    array = report_to_ros(
        {"alive": False}, name="robot1/presence", hardware_id="robot1", message="gone",
        stamp_ns=1, level=STALE,
    )  # fmt: skip
    assert array.status[0].level == STALE
    assert report_from_cdr(
        report_cdr(Command("c", 1, 1, 1.0), name="n", hardware_id="h", summary="", stamp_ns=1)
    ).fields == {"writer": "c", "seq": "1", "stamp_ns": "1", "value": "1.0"}


@pytest.mark.parametrize(
    ("pairs", "why"),
    [
        ([("a..b", "1")], "not a field path"),
        ([("[0]", "1")], "does not start with a field name"),
        ([("a", "1"), ("a", "2")], "given twice"),
        ([("a", "1"), ("a.b", "2")], "goes below a value"),
        ([("a[0]", "1"), ("a[2]", "2")], "list indices"),
        ([("a[0]", "1"), ("a.b", "2")], "both a list and a map"),
        ([("a[].b", "1")], "must end it"),
    ],
)
def test_malformed_key_values_are_refused_with_a_reason(
    pairs: list[tuple[str, str]], why: str
) -> None:
    with pytest.raises(ConversionError, match=why):
        unflatten(pairs)


def test_fields_of_another_message_are_refused() -> None:
    with pytest.raises(ConversionError, match="not a Telemetry"):
        from_fields(Telemetry, {"writer": "w", "seq": "x"}, strict=False)
    with pytest.raises(ConversionError, match="field 'seq' is missing"):
        from_fields(Command, {"writer": "w", "stamp_ns": 1, "value": 1.0})
    with pytest.raises(ConversionError, match="no field 'nope'"):
        from_fields(Command, {"nope": 1})


@given(
    st.dictionaries(
        st.text(min_size=1, max_size=8),
        st.one_of(
            st.integers(-(2**63), 2**63 - 1),
            st.floats(allow_nan=False),
            st.booleans(),
            st.text(max_size=8),
            st.lists(st.integers(0, 9), max_size=3),
        ),
        max_size=5,
    )
)
# keys spelled like the empty-list and empty-map markers (hypothesis found the first)
@example(data={"{}": 0, "[]": [], "x{}": {}})
def test_any_map_of_values_survives_the_key_value_form(data: dict[str, object]) -> None:
    back = unflatten(flatten({"m": data}))["m"]
    texts = {k: (v if isinstance(v, list) else str(v)) for k, v in back.items()}
    expected = {
        k: (
            [str(i) for i in v]
            if isinstance(v, list)
            else ("true" if v else "false")
            if isinstance(v, bool)
            else repr(v)
            if isinstance(v, float)
            else str(v)
        )
        for k, v in data.items()
    }
    assert texts == expected


# -- commands --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("value", "typename"),
    [
        ([0.8, -0.25], TWIST),
        ([1.0, 2.0, 3.0], FLOAT64_ARRAY),
        ([], FLOAT64_ARRAY),
        (0.1, FLOAT64),
        (True, BOOL),
        ("dock", STRING),
    ],
)
def test_a_command_value_comes_back_from_its_ros_message(value: object, typename: str) -> None:
    assert command_type(value) == typename  # type: ignore[arg-type]
    data = command_cdr(value, typename)  # type: ignore[arg-type]
    assert command_from_ros(deserialize(data, typename)) == value


def test_a_twist_is_what_ros2_topic_pub_cmd_vel_sends() -> None:
    twist = command_to_ros([0.5, 0.1], TWIST)
    assert (twist.linear.x, twist.linear.y, twist.linear.z) == (0.5, 0.0, 0.0)
    assert (twist.angular.x, twist.angular.y, twist.angular.z) == (0.0, 0.0, 0.1)


def test_a_command_of_another_type_than_its_channel_is_refused() -> None:
    with pytest.raises(ConversionError, match="is not a geometry_msgs/msg/Twist"):
        command_to_ros(1.0, TWIST)
    with pytest.raises(ConversionError, match="is not a command type"):
        command_from_ros(object())
