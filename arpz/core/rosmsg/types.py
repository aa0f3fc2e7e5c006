"""Which standard ROS 2 message type carries each of arpz's sensor kinds.

A ROS 2 user knows ``sensor_msgs/msg/LaserScan`` and ``sensor_msgs/msg/Imu``, not arpz's Table 1
value types, so every tool that shows or writes a topic (``topic list``, ``record``, Foxglove)
names these. The first type of each kind is the one a topic of that kind is converted to
(``arpz.core.rosmsg.convert``); docs/protocol.md "ROS 2 message types" gives the mapping field by
field and says why the Bool-like kinds use ``std_msgs/msg/Bool``.
"""

from __future__ import annotations

from typing import Final

from arpz.core.errors import ArpzError

#: sensor kind -> the standard ROS 2 types of its readings; the first is the topic's type.
#: dht11: arpz's DHT11 reading is the temperature (seed 001 Table 1 has one float), so its
#: topic is a Temperature; RelativeHumidity is listed because the device measures both and a
#: driver that reports humidity publishes it as that type.
ROS_TYPES: Final[dict[str, tuple[str, ...]]] = {
    "lidar": ("sensor_msgs/msg/LaserScan",),
    "imu": ("sensor_msgs/msg/Imu",),
    "ultrasonic": ("sensor_msgs/msg/Range",),
    "dht11": ("sensor_msgs/msg/Temperature", "sensor_msgs/msg/RelativeHumidity"),
    "light": ("sensor_msgs/msg/Illuminance",),
    "flame": ("std_msgs/msg/Bool",),
    "pir": ("std_msgs/msg/Bool",),
    "camera": ("sensor_msgs/msg/Image",),
    "pointcloud": ("sensor_msgs/msg/PointCloud2",),
}


class UnknownKindError(ArpzError, KeyError):
    """A sensor kind with no ROS 2 type (not one of arpz.core.config.SENSOR_KINDS)."""

    def __str__(self) -> str:  # KeyError quotes its argument; say it as a sentence instead
        return str(self.args[0])


def ros_types_for(kind: str) -> tuple[str, ...]:
    """The standard ROS 2 types of ``kind``'s readings, the topic's own type first."""
    try:
        return ROS_TYPES[kind]
    except KeyError:
        known = ", ".join(sorted(ROS_TYPES))
        raise UnknownKindError(
            f"sensor kind {kind!r} has no ROS 2 message type: use one of {known}"
        ) from None


def ros_type_for(kind: str) -> str:
    """The ROS 2 type a topic of ``kind`` is converted to (the first of ``ros_types_for``)."""
    return ros_types_for(kind)[0]
