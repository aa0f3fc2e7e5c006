"""Typed messages (arpz.core.msgtypes): every standard ROS 2 type and a team's own, checked at the
boundary, carried as msgpack, converted to CDR and back exactly."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from arpz import ArpzError
from arpz.core.msgtypes import MessageTypeError, MessageTypes, MessageValueError

NAVSAT = "sensor_msgs/msg/NavSatFix"
SCAN = "sensor_msgs/msg/LaserScan"


@pytest.fixture(scope="module")
def types() -> MessageTypes:
    return MessageTypes()


def navsat(**changes: Any) -> dict[str, Any]:
    fix = {
        "status": {"status": 0, "service": 1},
        "latitude": 51.4545,
        "longitude": -2.5879,
        "altitude": 11,
        "position_covariance": [0.0] * 9,
        "position_covariance_type": 2,
    }
    return {**fix, **changes}


def scan(ranges: list[float] | np.ndarray) -> dict[str, Any]:
    return {
        "angle_min": -1.5,
        "angle_max": 1.5,
        "angle_increment": 0.1,
        "time_increment": 0.0,
        "scan_time": 0.1,
        "range_min": 0.12,
        "range_max": 12.0,
        "ranges": ranges,
        "intensities": [],
    }


def test_every_standard_package_is_known_without_ros2(types: MessageTypes) -> None:
    names = types.names()
    for package in ("std_msgs", "sensor_msgs", "geometry_msgs", "nav_msgs", "diagnostic_msgs"):
        assert any(name.startswith(f"{package}/msg/") for name in names), package
    assert len(names) > 140


def test_a_dict_is_checked_into_the_wire_struct_and_stamped(types: MessageTypes) -> None:
    fix = types.check(NAVSAT, navsat(), stamp_ns=1_733_400_000_123_456_789, frame_id="gps")
    assert fix.latitude == 51.4545 and fix.altitude == 11.0
    assert (fix.header.stamp.sec, fix.header.stamp.nanosec) == (1_733_400_000, 123_456_789)
    assert fix.header.frame_id == "gps"
    assert types.decode(NAVSAT, types.encode(fix)) == fix


@pytest.mark.parametrize(
    ("changes", "says"),
    [
        ({"latitude": "north"}, "$.latitude"),
        ({"bogus": 1}, "unknown field `bogus`"),
        ({"status": {"status": 300, "service": 1}}, "$.status.status"),
        ({"position_covariance": [0.0] * 8}, "$.position_covariance"),
        ({"latitude": math.nan}, "NavSatFix.latitude is nan"),
        ({"altitude": -math.inf}, "NavSatFix.altitude is -inf"),
    ],
)
def test_a_message_that_does_not_fit_is_refused_naming_the_field(
    types: MessageTypes, changes: dict[str, Any], says: str
) -> None:
    with pytest.raises(MessageValueError, match=None) as caught:
        types.check(NAVSAT, navsat(**changes), stamp_ns=1)
    assert says in str(caught.value)
    assert isinstance(caught.value, ArpzError)


def test_a_missing_field_is_refused(types: MessageTypes) -> None:
    fields = navsat()
    del fields["status"]
    with pytest.raises(MessageValueError, match="missing required field `status`"):
        types.check(NAVSAT, fields, stamp_ns=1)


def test_refuse_lets_a_scans_inf_through_refuse_all_does_not(types: MessageTypes) -> None:
    ranges = np.array([1.0, math.inf, math.nan], dtype=np.float32)
    kept = types.check(SCAN, scan(ranges), stamp_ns=1)
    assert kept.ranges[1] == math.inf and math.isnan(kept.ranges[2])
    with pytest.raises(MessageValueError, match="ranges holds a NaN"):
        types.check(SCAN, scan(ranges), stamp_ns=1, nan="refuse_all")
    passed = types.check(NAVSAT, navsat(latitude=math.nan), stamp_ns=1, nan="pass")
    assert math.isnan(passed.latitude)


def test_cdr_both_ways_is_exact_and_is_what_rosbags_reads(types: MessageTypes) -> None:
    store = get_typestore(Stores.ROS2_HUMBLE)
    for name, fields in [(NAVSAT, navsat()), (SCAN, scan([1.1, 2.25, 3.3]))]:
        message = types.check(name, fields, stamp_ns=42, frame_id="base")
        cdr = types.to_cdr(name, message)
        assert types.from_cdr(name, cdr) == message
        as_rosbags = store.deserialize_cdr(cdr, name)
        assert as_rosbags.header.frame_id == "base"
    # float32 fields hold float32 values, so the round trip is exact
    laser = types.check(SCAN, scan([1.1]), stamp_ns=1)
    assert laser.angle_increment == float(np.float32(0.1))


def test_an_image_carries_its_pixels_as_bytes(types: MessageTypes) -> None:
    pixels = np.arange(12, dtype=np.uint8)
    image = types.check(
        "sensor_msgs/msg/Image",
        {"height": 2, "width": 2, "encoding": "rgb8", "is_bigendian": 0, "step": 6, "data": pixels},
        stamp_ns=1,
    )
    assert image.data == pixels.tobytes()
    assert (
        types.from_cdr("sensor_msgs/msg/Image", types.to_cdr("sensor_msgs/msg/Image", image))
        == image
    )


def test_a_rosbags_message_object_is_taken_by_its_attributes(types: MessageTypes) -> None:
    store = get_typestore(Stores.ROS2_HUMBLE)
    raw = types.to_cdr(NAVSAT, types.check(NAVSAT, navsat(), stamp_ns=7))
    as_object = store.deserialize_cdr(raw, NAVSAT)
    assert types.check(NAVSAT, as_object).latitude == 51.4545


def test_unknown_type_names_say_what_to_write(types: MessageTypes) -> None:
    with pytest.raises(MessageTypeError, match="package/msg/Name"):
        types.require("gps")
    with pytest.raises(MessageTypeError, match="did you mean sensor_msgs/msg/NavSatFix"):
        types.require("sensor_msgs/msg/NavSatFx")
    with pytest.raises(MessageTypeError, match=r"sensor_msgs has .*NavSatFix"):
        types.require("sensor_msgs/msg/Gps")


def test_the_type_hash_is_ros2s(types: MessageTypes) -> None:
    # the RIHS01 of sensor_msgs/msg/NavSatFix as ROS 2 (Humble and later) computes it
    assert types.type_hash(NAVSAT) == (
        "RIHS01_62223ab3fe210a15976021da7afddc9e200dc9ec75231c1b6a557fc598a65404"
    )


def test_a_teams_types_come_from_msg_files(tmp_path: Path) -> None:
    folder = tmp_path / "msg" / "mylab" / "msg"
    folder.mkdir(parents=True)
    (folder / "Battery.msg").write_text(
        "uint8 FULL=100\nstd_msgs/Header header\nfloat32 percent\nbool charging\n"
    )
    (folder / "Dock.msg").write_text("mylab/Battery battery\nstring name\n")
    types = MessageTypes()
    assert types.add_msg_paths([tmp_path / "msg"]) == ["mylab/msg/Battery", "mylab/msg/Dock"]
    dock = types.check(
        "mylab/msg/Dock",
        {
            "battery": {
                "percent": 20.5,
                "charging": False,
                "header": {"stamp": {"sec": 1, "nanosec": 0}, "frame_id": ""},
            },
            "name": "d1",
        },
    )
    assert dock.battery.percent == 20.5
    assert types.struct("mylab/msg/Battery").FULL == 100
    assert types.type_hash("mylab/msg/Battery").startswith("RIHS01_")
    assert "float32 percent" in types.definition("mylab/msg/Battery")


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("flot32 percent\n", "names type 'mylab/msg/flot32'"),
        ("float32 percent\nfloat32[ bad\n", "not a valid .msg definition"),
    ],
)
def test_a_bad_msg_file_is_refused_naming_the_file(tmp_path: Path, text: str, says: str) -> None:
    folder = tmp_path / "mylab" / "msg"
    folder.mkdir(parents=True)
    (folder / "Battery.msg").write_text(text)
    with pytest.raises(MessageTypeError) as caught:
        MessageTypes().add_msg_paths([tmp_path])
    assert "Battery.msg" in str(caught.value) and says in str(caught.value)


def test_a_msg_file_outside_a_msg_folder_is_refused(tmp_path: Path) -> None:
    (tmp_path / "Battery.msg").write_text("float32 percent\n")
    with pytest.raises(MessageTypeError, match="PACKAGE/msg/"):
        MessageTypes().add_msg_paths([tmp_path])


def test_a_python_class_becomes_a_type() -> None:
    @dataclasses.dataclass
    class Battery:
        ros_type = "mylab/msg/Battery"
        percent: float
        charging: bool
        cells: list[float]

    types = MessageTypes()
    assert types.register_class(Battery) == "mylab/msg/Battery"
    message = types.check("mylab/msg/Battery", Battery(50.0, True, [3.7, 3.8]))
    assert (message.percent, message.charging, message.cells) == (50.0, True, [3.7, 3.8])
    assert isinstance(message, msgspec.Struct)
