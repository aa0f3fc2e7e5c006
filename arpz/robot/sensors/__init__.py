"""Sensor drivers: the seven simulated kinds of seed 001 Table 1, trace replay, and the interface
a user implements for real hardware (see docs/sensors.md)."""

from arpz.robot.sensors.base import SensorDriver, value_type_of
from arpz.robot.sensors.factory import make_driver
from arpz.robot.sensors.presets import PRESETS, preset_sensors

__all__ = ["PRESETS", "SensorDriver", "make_driver", "preset_sensors", "value_type_of"]
