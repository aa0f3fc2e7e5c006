"""The robot side of arpz: sensing through a local cache, actuation, presence.

The public API of a robot: ``RobotAgent`` (run by ``python -m arpz.robot``, or embedded), and the
two bases a team extends for its hardware, ``SensorDriver`` and ``Actuator`` (docs/api.md).
Everything else in this package is internal.
"""

from arpz.robot.actuation import Actuator, RecordingActuator
from arpz.robot.agent import RobotAgent
from arpz.robot.sensors.base import SensorDriver
from arpz.robot.sensors.factory import make_driver

__all__ = ["Actuator", "RecordingActuator", "RobotAgent", "SensorDriver", "make_driver"]
