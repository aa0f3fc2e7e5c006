"""arpz command values as standard ROS 2 messages, exactly (what ``arpz record`` writes).

A command's value (``arpz.core.messages.CommandValue``) is a float, a bool, a string or a vector
of floats. Each has a standard ROS 2 type that holds it unchanged (every float is float64):

- ``[v, omega]`` (the differential-drive ``velocity`` of the simulated body and the bridge) is a
  ``geometry_msgs/msg/Twist`` with ``linear.x = v`` and ``angular.z = omega``, the message
  ``ros2 topic pub /robot1/cmd_vel`` sends and the bridge turns back into the same pair
  (arpz/bridge/commands.py); its other four components are 0;
- any other vector is a ``std_msgs/msg/Float64MultiArray`` (no layout: ``data`` alone);
- a float, a bool and a string are ``std_msgs/msg/Float64``, ``Bool`` and ``String``.

None of these has a header: a recording keeps the command's stamp as the message's log time.
"""

from __future__ import annotations

from typing import Any, Final

import numpy as np

from arpz.core.messages import CommandValue
from arpz.core.rosmsg.convert import STORE, ConversionError, serialize

TWIST: Final = "geometry_msgs/msg/Twist"
FLOAT64: Final = "std_msgs/msg/Float64"
BOOL: Final = "std_msgs/msg/Bool"
STRING: Final = "std_msgs/msg/String"
FLOAT64_ARRAY: Final = "std_msgs/msg/Float64MultiArray"
#: every ROS 2 type a command value becomes
COMMAND_TYPES: Final = (TWIST, FLOAT64, BOOL, STRING, FLOAT64_ARRAY)


def command_type(value: CommandValue) -> str:
    """The ROS 2 type that holds ``value``."""
    if isinstance(value, bool):
        return BOOL
    if isinstance(value, float | int):
        return FLOAT64
    if isinstance(value, str):
        return STRING
    if isinstance(value, list) and all(isinstance(v, float | int) for v in value):
        return TWIST if len(value) == 2 else FLOAT64_ARRAY
    raise ConversionError(f"command value {value!r} has no ROS 2 type")


def command_to_ros(value: CommandValue, typename: str) -> Any:
    """The ``typename`` message (a rosbags typestore object) of ``value``;
    ``ConversionError`` when ``value`` is not of that type (a command channel keeps the type
    of its first command)."""
    if command_type(value) != typename:
        raise ConversionError(f"command value {value!r} is not a {typename}")
    types = STORE.types
    if typename == TWIST:
        assert isinstance(value, list)
        vector = types["geometry_msgs/msg/Vector3"]
        return types[TWIST](
            linear=vector(x=float(value[0]), y=0.0, z=0.0),
            angular=vector(x=0.0, y=0.0, z=float(value[1])),
        )
    if typename == FLOAT64_ARRAY:
        assert isinstance(value, list)
        layout = types["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0)
        return types[FLOAT64_ARRAY](layout=layout, data=np.array(value, dtype=np.float64))
    if typename == FLOAT64:
        assert isinstance(value, float | int)
        return types[FLOAT64](data=float(value))
    return types[typename](data=value)


def command_from_ros(message: Any) -> CommandValue:
    """The command value of a message ``command_to_ros`` made (the reverse, exactly)."""
    typename = getattr(message, "__msgtype__", None)
    if typename == TWIST:
        return [float(message.linear.x), float(message.angular.z)]
    if typename == FLOAT64_ARRAY:
        return [float(v) for v in message.data]
    if typename == FLOAT64:
        return float(message.data)
    if typename == BOOL:
        return bool(message.data)
    if typename == STRING:
        return str(message.data)
    raise ConversionError(f"{typename!r} is not a command type ({', '.join(COMMAND_TYPES)})")


def command_cdr(value: CommandValue, typename: str) -> bytes:
    """``value`` as the CDR of its ``typename`` message."""
    return serialize(command_to_ros(value, typename))
