"""Build the driver a SensorConfig asks for: simulated, replay, or a user class by import path."""

from __future__ import annotations

import zlib
from pathlib import Path

from arpz.core.config import SensorConfig
from arpz.core.errors import ArpzError
from arpz.robot.sensors.base import SensorDriver
from arpz.robot.sensors.replay import ReplayDriver
from arpz.robot.sensors.simulated import SIMULATED, SIMULATED_MESSAGES
from arpz.runtime.plugins import PluginError, load_class


class DriverError(ArpzError, ValueError):
    """A driver that cannot be created; the message names the sensor and the cause."""


def sensor_seed(robot_seed: int, robot_id: str, sensor: SensorConfig) -> int:
    """A stable per-sensor seed, so robots with the same config do not produce identical streams."""
    if sensor.seed is not None:
        return sensor.seed
    return zlib.crc32(f"{robot_seed}/{robot_id}/{sensor.name}".encode())


def make_driver(
    sensor: SensorConfig, *, robot_id: str, robot_seed: int, base_dir: Path
) -> SensorDriver:
    seed = sensor_seed(robot_seed, robot_id, sensor)
    if sensor.driver == "sim":
        try:
            if sensor.type is not None:  # one of SIMULATED_TYPES: checked by SensorConfig
                return SIMULATED_MESSAGES[sensor.type](sensor.options, seed, rate_hz=sensor.rate_hz)
            return SIMULATED[sensor.kind](sensor.options, seed)
        except (ValueError, TypeError) as exc:
            what = sensor.type or sensor.kind
            raise DriverError(f"sensor {sensor.name!r} ({what}): {exc}") from None
    if sensor.driver == "replay":
        assert sensor.trace is not None  # checked by SensorConfig
        trace = Path(sensor.trace)
        return ReplayDriver(
            sensor.kind, trace if trace.is_absolute() else base_dir / trace, sensor.options, seed
        )
    if ":" not in sensor.driver:
        raise DriverError(
            f"sensor {sensor.name!r}: driver must be 'sim', 'replay' or 'module.path:ClassName', "
            f"got {sensor.driver!r}"
        )
    try:
        cls = load_class(sensor.driver, SensorDriver, setting=f"sensor {sensor.name!r}: driver")
    except PluginError as exc:
        raise DriverError(str(exc)) from None
    if cls.kind and cls.kind != sensor.kind:
        raise DriverError(
            f"sensor {sensor.name!r}: driver {sensor.driver!r} reads {cls.kind!r}, "
            f"config says {sensor.kind!r}"
        )
    driver: SensorDriver = cls(sensor.options, seed)
    return driver
