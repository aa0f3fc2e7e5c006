"""Planners and actuators a team would write, loaded by a real CEDDP and a real robot from
their TOMLs in tests/integration/test_team_nodes.py."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from arpz.ceddp.planner import Planner, Reading
from arpz.core.messages import Command
from arpz.robot.actuation import Actuator


class CountingPlanner(Planner):
    """Writes how many readings of each topic it saw, and whether it was attached and started,
    to ``options.out`` on every reading (the test reads the file back)."""

    def __init__(self, options: Mapping[str, Any]) -> None:
        super().__init__(options)
        self.out = Path(str(options["out"]))
        self.seen: dict[str, int] = {}
        self.started = False

    def start(self) -> None:
        self.started = True

    def on_reading(self, reading: Reading) -> None:
        key = f"{reading.robot}/{reading.topic}"
        self.seen[key] = self.seen.get(key, 0) + 1
        state = {"seen": self.seen, "started": self.started, "attached": self.commands is not None}
        partial = self.out.with_suffix(".partial")
        partial.write_text(json.dumps(state))
        partial.replace(self.out)


class RaisingPlanner(Planner):
    """Raises on every reading: the CEDDP must count it and go on."""

    def on_reading(self, reading: Reading) -> None:
        raise ZeroDivisionError(f"reading of {reading.topic} divided by zero")


class NeedsOptions(Planner):
    """Refuses to be made without its option (a bad [[planners]] entry)."""

    def __init__(self, options: Mapping[str, Any]) -> None:
        super().__init__(options)
        self.threshold = float(options["threshold"])


class Commander(Planner):
    """Sends robot1 a velocity command every ``period_s`` of readings, through the planner's
    command sink (``self.commands``)."""

    def __init__(self, options: Mapping[str, Any]) -> None:
        super().__init__(options)
        self.period_ns = int(float(options.get("period_s", 0.05)) * 1e9)
        self.last_ns = 0

    def on_reading(self, reading: Reading) -> None:
        if reading.robot == "robot1" and reading.arrival_ns - self.last_ns >= self.period_ns:
            self.last_ns = reading.arrival_ns
            assert self.commands is not None
            self.commands.send(reading.robot, "velocity", [0.25, -0.5])


class FileActuator(Actuator):
    """Acts on "velocity" by writing what it got to ``options.out`` (the test reads it back)."""

    commands = ("velocity",)

    def __init__(self, options: Mapping[str, Any]) -> None:
        super().__init__(options)
        self.out = Path(str(options["out"]))
        self.applied = 0
        self.safe_stops = 0

    def apply(self, name: str, command: Command) -> None:
        self.applied += 1
        self._write({"name": name, "value": command.value, "applied": self.applied})

    def safe_stop(self) -> None:
        self.safe_stops += 1

    def _write(self, state: dict[str, Any]) -> None:
        partial = self.out.with_suffix(".partial")
        partial.write_text(json.dumps(state))
        partial.replace(self.out)


class Mute(Actuator):
    """An actuator that forgot to say what it acts on."""


class StampedDriver(Planner):
    """Declares it sends cmd_vel as a TwistStamped: a robot whose actuator takes a Twist must
    refuse to start."""

    sends = {"cmd_vel": "geometry_msgs/msg/TwistStamped"}  # noqa: RUF012
