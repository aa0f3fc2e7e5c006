"""ROS 2 command messages -> arpz command values (docs/ros2.md "Commands").

The simulated body (arpz/robot/sim_host.py) and any differential-drive actuator take
``velocity`` as ``[v_m_s, omega_rad_s]``: a ``geometry_msgs/msg/Twist`` gives its
``linear.x`` and ``angular.z`` (the other four components have no meaning for a planar robot
and are ignored, as a differential-drive base controller ignores them). The std_msgs types carry
one scalar each.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Final

from arpz.core.messages import CommandValue


def _twist(message: Any) -> CommandValue:
    return [float(message.linear.x), float(message.angular.z)]


#: ROS 2 type -> its arpz command value; the keys are arpz.core.config.ROS2_COMMAND_TYPES
CONVERTERS: Final[dict[str, Callable[[Any], CommandValue]]] = {
    "geometry_msgs/msg/Twist": _twist,
    "std_msgs/msg/Float64": lambda m: float(m.data),
    "std_msgs/msg/Bool": lambda m: bool(m.data),
    "std_msgs/msg/String": lambda m: str(m.data),
}


def command_value(ros_type: str, message: Any) -> CommandValue:
    """The arpz command value of a decoded ROS 2 message of ``ros_type``."""
    return CONVERTERS[ros_type](message)
