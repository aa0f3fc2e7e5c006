"""Every sensor kind has a standard ROS 2 type that rosbags' ROS 2 typestore knows."""

from __future__ import annotations

import pytest
from rosbags.typesys import Stores, get_typestore

from arpz.core.config import SENSOR_KINDS
from arpz.core.rosmsg.types import ROS_TYPES, UnknownKindError, ros_type_for, ros_types_for


def test_every_sensor_kind_has_types_known_to_the_ros2_typestore() -> None:
    store = get_typestore(Stores.ROS2_HUMBLE)
    assert set(ROS_TYPES) == set(SENSOR_KINDS)
    for kind in SENSOR_KINDS:
        for name in ros_types_for(kind):
            assert name in store.fielddefs, name


def test_the_topic_type_is_the_first() -> None:
    assert ros_type_for("dht11") == "sensor_msgs/msg/Temperature"
    assert ros_types_for("lidar") == ("sensor_msgs/msg/LaserScan",)


def test_an_unknown_kind_is_an_error_naming_the_known_ones() -> None:
    with pytest.raises(UnknownKindError, match="'sonar' has no ROS 2 message type: use one of"):
        ros_types_for("sonar")
