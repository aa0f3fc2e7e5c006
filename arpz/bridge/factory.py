"""The bridge a ``[ros2]`` config asks for (docs/ros2.md "Backends"): ``backend = "rmw_zenoh"``
(the default: rmw_zenoh's protocol on the fleet's router, no ROS 2 installed) or ``"rclpy"``
(a real ROS 2 node on the host's RMW, ``arpz.bridge.rclpy_backend``, imported only then)."""

from __future__ import annotations

from arpz.bridge.bridge import Bridge
from arpz.core.config import Ros2Config
from arpz.core.errors import ConfigError

#: how to get rclpy and the standard message packages from the package index
INSTALL_HINT = "pip install 'arpz[ros2]'"


class Ros2Unavailable(ConfigError):
    """``backend = "rclpy"`` where rclpy does not import or ROS 2 does not start (the text says
    why and how to install it)."""


def bridge_class(config: Ros2Config) -> type[Bridge]:
    """The bridge class of ``config.backend``, made as ``Bridge`` is. Raises ``Ros2Unavailable``
    for the rclpy backend when rclpy does not import."""
    if config.backend != "rclpy":
        return Bridge
    try:
        from arpz.bridge.rclpy_backend import RclpyBridge
    except ImportError as exc:
        raise Ros2Unavailable(
            f'[ros2] backend = "rclpy" needs ROS 2\'s rclpy, which does not import here ({exc}): '
            f'{INSTALL_HINT} (or source a ROS 2 installation), or use backend = "rmw_zenoh"'
        ) from None
    return RclpyBridge
