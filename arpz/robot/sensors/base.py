"""The driver interface: one small class per sensor.

A driver is asked for a reading at the sensor's configured rate; it returns the typed value of
seed 001 Table 1. The agent owns timing, the local cache and publishing, so a hardware driver
only has to read its device. Example (a GPIO PIR sensor)::

    class GpioPir(SensorDriver):
        kind = "pir"

        def __init__(self, options: dict[str, object], seed: int) -> None:
            self._pin = open_gpio(int(options["pin"]))

        def read(self, now_s: float) -> str:
            return "detect" if self._pin.value else "not detect"

and in robot.toml: ``driver = "mypackage.sensors:GpioPir"`` with ``options = { pin = 17 }``.
"""

from __future__ import annotations

from typing import Any, ClassVar, cast

from arpz.core.errors import ArpzError
from arpz.core.messages import SensorValue

#: the Python type of each kind's value, as Table 1 of seed 001 gives it
VALUE_TYPES: dict[str, type] = {
    "lidar": float,
    "dht11": float,
    "imu": float,
    "ultrasonic": float,
    "flame": bool,
    "pir": str,
    "light": str,
    # beyond Table 1: large readings, as raw bytes (layouts in docs/sensors.md)
    "camera": bytes,
    "pointcloud": bytes,
}

STRING_VALUES: dict[str, tuple[str, str]] = {
    "pir": ("detect", "not detect"),
    "light": ("light", "dark"),
}


def value_type_of(kind: str) -> str:
    return VALUE_TYPES[kind].__name__


class SensorDriver:
    """Base class of every driver. Subclasses set ``kind`` and implement ``read``."""

    kind: ClassVar[str] = ""

    def __init__(self, options: dict[str, Any], seed: int) -> None:
        self.options = options
        self.seed = seed

    def read(self, now_s: float) -> SensorValue | Any:
        """The reading at ``now_s`` seconds since the agent started: the value of its kind, or
        a typed sensor's message (a dict of its fields, numpy arrays allowed, or the message
        as an object; the robot checks it against the type, docs/nodes.md)."""
        raise NotImplementedError

    def close(self) -> None:
        """Release the device; called once when the agent stops."""


class DriverValueError(ArpzError, TypeError):
    """A driver returned a value of the wrong type for its kind."""


def check_value(kind: str, value: object) -> SensorValue:
    """Make sure a driver's value has the Table 1 type; ints are accepted for float kinds.

    Called for every reading (40 000 a second in ``python -m arpz.perf fleet``): a value of
    exactly its kind's type is checked first and returned as it is."""
    expected = VALUE_TYPES[kind]
    if type(value) is expected:
        allowed = STRING_VALUES.get(kind)
        if allowed is None or value in allowed:
            return cast(SensorValue, value)
        choices = " or ".join(repr(v) for v in allowed)
        raise DriverValueError(f"a {kind} driver must return {choices}, got {value!r}")
    if expected is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    got = f"{type(value).__name__}: {value!r:.80}"
    raise DriverValueError(f"a {kind} driver must return {expected.__name__}, got {got}")
