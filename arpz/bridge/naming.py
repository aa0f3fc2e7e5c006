"""Which ROS 2 topic each arpz topic and command becomes (docs/ros2.md "Topics").

A topic named after its kind (the presets' ``lidar``, ``imu``, ...) takes the name a ROS 2 user
expects for that sensor (``/robot1/scan``, ``/robot1/imu``); any other topic keeps its own name
under the robot's namespace (``/robot1/lidar_0`` for a simulated body's beam, ``/robot1/front``
for a camera named front). ``[ros2] topics`` overrides either, per robot or for every robot.
ROS 2 names allow letters, digits and '_': an arpz '-' becomes '_'.
"""

from __future__ import annotations

from typing import Final

from arpz.core.config import Ros2Config

#: the ROS 2 name of a topic named after its kind (the convention of the ROS 2 drivers of
#: such sensors: ``scan`` for a planar LIDAR, ``image_raw`` for a camera, ``points`` for a cloud)
DEFAULT_NAMES: Final[dict[str, str]] = {
    "lidar": "scan",
    "imu": "imu",
    "camera": "image_raw",
    "pointcloud": "points",
    "ultrasonic": "range",
    "dht11": "temperature",
    "light": "illuminance",
    "flame": "flame",
    "pir": "motion",
}


def ros_token(name: str) -> str:
    """An arpz key chunk as a ROS 2 name token ('-' -> '_', a leading digit gets a '_')."""
    token = name.replace("-", "_")
    return f"_{token}" if token[:1].isdigit() else token


def fill(template: str, robot: str, topic: str = "") -> str:
    return template.replace("{robot}", ros_token(robot)).replace("{topic}", ros_token(topic))


def topic_name(config: Ros2Config, robot: str, topic: str, kind: str) -> str:
    """The ROS 2 topic of ``robot``'s arpz ``topic`` of ``kind``."""
    template = config.topics.get(f"{robot}/{topic}") or config.topics.get(f"*/{topic}")
    if template is None:
        default = DEFAULT_NAMES.get(kind) if topic == kind else None
        template = f"/{{robot}}/{default}" if default else "/{robot}/{topic}"
    return fill(template, robot, topic)


def service_name(robot: str, service: str) -> str:
    """The ROS 2 service of ``robot``'s arpz service ``service`` (``/robot1/dock``)."""
    return f"/{ros_token(robot)}/{ros_token(service)}"


def command_key_expr(domain_id: int, template: str) -> str:
    """The key expression of every robot's command topic of one mapping (``{robot}`` as ``*``):
    one Zenoh subscriber serves the whole fleet. Any type is matched on purpose, so a message
    of another type on the topic is seen and counted, not silently missed."""
    return f"{domain_id}/{template.strip('/').replace('{robot}', '*')}/*/*"


def frame_id(robot: str, topic: str) -> str:
    """The ``header.frame_id`` of a bridged message."""
    return f"{ros_token(robot)}/{ros_token(topic)}"
