"""arpz reading -> ROS 2 message -> CDR -> arpz reading is the identity, and ROS 2 -> arpz ->
ROS 2 gives the same CDR bytes (docs/protocol.md "ROS 2 message types")."""

from __future__ import annotations

import math
from decimal import Decimal

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from arpz.core.messages import SensorValue
from arpz.core.rosmsg.convert import (
    CDR_LE_HEADER,
    ConversionError,
    deserialize,
    from_cdr,
    from_ros,
    is_exact,
    message_definition,
    serialize,
    to_cdr,
    to_ros,
)
from arpz.core.rosmsg.types import ROS_TYPES, ros_type_for
from arpz.robot.sensors.simulated import SIMULATED

STAMPS = st.integers(0, 2**31 * 1_000_000_000 - 1)
FRAMES = st.text(max_size=20)


def decimals(max_digits: int = 6) -> st.SearchStrategy[float]:
    """Readings as sensors give them: at most ``max_digits`` significant decimal digits."""
    return st.builds(
        lambda n, e: float(Decimal(n).scaleb(e)),
        st.integers(-(10**max_digits) + 1, 10**max_digits - 1),
        st.integers(-6, 3),
    )


def values(kind: str) -> st.SearchStrategy[SensorValue]:
    if kind in ("lidar", "ultrasonic"):
        return decimals()
    if kind in ("dht11", "imu"):
        return st.floats(allow_nan=False)
    if kind == "flame":
        return st.booleans()
    if kind == "pir":
        return st.sampled_from(["detect", "not detect"])
    if kind == "light":
        return st.sampled_from(["light", "dark"])
    if kind == "camera":
        return st.binary(max_size=150).map(lambda b: b[: len(b) - len(b) % 3])
    return st.binary(max_size=120).map(lambda b: b[: len(b) - len(b) % 12])


@pytest.mark.parametrize("kind", sorted(ROS_TYPES))
@given(data=st.data(), stamp_ns=STAMPS, frame_id=FRAMES)
def test_a_reading_comes_back_unchanged_through_cdr(
    kind: str, data: st.DataObject, stamp_ns: int, frame_id: str
) -> None:
    value = data.draw(values(kind))
    cdr = to_cdr(kind, value, stamp_ns=stamp_ns, frame_id=frame_id)
    assert cdr[:4] == CDR_LE_HEADER
    back = from_cdr(kind, cdr)
    assert type(back.value) is type(value)
    assert back.value == value
    assert is_exact(kind, value)
    if kind in ("flame", "pir"):  # std_msgs/msg/Bool: no header
        assert back.stamp_ns is None and back.frame_id is None
    else:
        assert back.stamp_ns == stamp_ns and back.frame_id == frame_id


@pytest.mark.parametrize("kind", sorted(ROS_TYPES))
@given(data=st.data(), stamp_ns=STAMPS, frame_id=FRAMES)
def test_a_message_comes_back_as_the_same_cdr(
    kind: str, data: st.DataObject, stamp_ns: int, frame_id: str
) -> None:
    cdr = to_cdr(kind, data.draw(values(kind)), stamp_ns=stamp_ns, frame_id=frame_id)
    reading = from_cdr(kind, cdr)
    again = to_cdr(kind, reading.value, stamp_ns=stamp_ns, frame_id=frame_id)
    assert again == cdr


@given(st.floats(width=32))
def test_any_float32_range_survives_ros_to_arpz_to_ros(range_m: float) -> None:
    for kind, field in (("lidar", "ranges"), ("ultrasonic", "range")):
        message = to_ros(kind, 1.0, stamp_ns=0, frame_id="f")
        if field == "ranges":
            message.ranges[0] = range_m
        else:
            message.range = range_m
        reading = from_ros(kind, message)
        again = to_ros(kind, reading.value, stamp_ns=0, frame_id="f")
        got = float(again.ranges[0] if field == "ranges" else again.range)
        assert got == range_m or (math.isnan(got) and math.isnan(range_m)), kind


def test_more_digits_than_float32_keeps_are_reported_not_exact() -> None:
    assert not is_exact("lidar", 1.2345678901)
    assert is_exact("lidar", 12.34)
    assert is_exact("dht11", 1.2345678901)  # float64 in ROS 2


@pytest.mark.parametrize("kind", sorted(SIMULATED))
def test_every_simulated_driver_converts_exactly(kind: str) -> None:
    options = {"width": 8, "height": 16} if kind == "camera" else {"points": 10}
    driver = SIMULATED[kind](options if kind in ("camera", "pointcloud") else {}, seed=3)
    for i in range(200):
        value = driver.read(i * 0.05)
        assert from_cdr(kind, to_cdr(kind, value, stamp_ns=i, frame_id="r/t")).value == value


def test_the_fields_a_ros_user_reads() -> None:
    scan = to_ros("lidar", 2.37, stamp_ns=1_500_000_000, frame_id="robot1/lidar_0")
    assert scan.header.stamp.sec == 1 and scan.header.stamp.nanosec == 500_000_000
    assert scan.header.frame_id == "robot1/lidar_0"
    assert list(scan.ranges) == [np.float32(2.37)]
    assert to_ros("ultrasonic", 123.3, stamp_ns=0, frame_id="").range == np.float32(1.233)
    imu = to_ros("imu", 9.80665, stamp_ns=0, frame_id="")
    assert imu.linear_acceleration.z == 9.80665 and imu.orientation_covariance[0] == -1.0
    image = to_ros("camera", bytes(640 * 480 * 3), stamp_ns=0, frame_id="")
    assert (image.width, image.height, image.step, image.encoding) == (640, 480, 1920, "rgb8")
    cloud = to_ros("pointcloud", bytes(24), stamp_ns=0, frame_id="")
    assert (cloud.width, cloud.point_step, [f.name for f in cloud.fields]) == (2, 12, list("xyz"))
    assert to_ros("pir", "detect", stamp_ns=0, frame_id="").data is True
    assert to_ros("light", "dark", stamp_ns=0, frame_id="").illuminance == 0.0


def test_values_without_a_counterpart_are_errors_that_say_so() -> None:
    with pytest.raises(ConversionError, match="pir value 'maybe' has no std_msgs/msg/Bool"):
        to_ros("pir", "maybe", stamp_ns=0, frame_id="")
    with pytest.raises(ConversionError, match="not whole RGB pixels"):
        to_ros("camera", b"1234", stamp_ns=0, frame_id="")
    with pytest.raises(ConversionError, match="outside builtin_interfaces/Time"):
        to_ros("dht11", 1.0, stamp_ns=2**31 * 10**9, frame_id="")
    with pytest.raises(ConversionError, match="not a CDR sensor_msgs/msg/Imu"):
        deserialize(b"\x00\x01\x00\x00\x01", "sensor_msgs/msg/Imu")
    with pytest.raises(ConversionError, match="a lidar reading is a sensor_msgs/msg/LaserScan"):
        from_ros("lidar", to_ros("dht11", 1.0, stamp_ns=0, frame_id=""))


def test_message_definitions_carry_their_dependencies() -> None:
    text = message_definition(ros_type_for("lidar"))
    assert text.startswith("std_msgs/Header header") and "MSG: builtin_interfaces/Time" in text
    assert serialize(to_ros("flame", True, stamp_ns=0, frame_id="")) == CDR_LE_HEADER + b"\x01"
