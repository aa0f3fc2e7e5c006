"""The lab's planner: drives each robot slower as its battery drains (a Twist on cmd_vel), and
sends a robot whose battery falls under ``threshold`` to its dock (then stops driving it: its
watchdog stops it)."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any

from arpz.ceddp import Planner, Reading

log = logging.getLogger(__name__)


class DockPlanner(Planner):
    def __init__(self, options: Mapping[str, Any]) -> None:
        super().__init__(options)
        self.threshold = float(options.get("threshold", 0.2))
        self.slow_below = float(options.get("slow_below", 0.25))
        self.sent: set[str] = set()

    def on_reading(self, reading: Reading) -> None:
        if reading.topic == "battery":
            battery: Any = reading.value  # sensor_msgs/msg/BatteryState
            if reading.robot not in self.sent and self.commands is not None:
                speed = 0.5 if battery.percentage > self.slow_below else 0.2
                still = {"x": 0.0, "y": 0.0, "z": 0.0}
                twist = {"linear": {"x": speed, "y": 0.0, "z": 0.0}, "angular": still}
                self.commands.send(reading.robot, "cmd_vel", twist)
            if battery.percentage < self.threshold and reading.robot not in self.sent:
                assert self.commands is not None
                self.commands.send(reading.robot, "dock", True)
                self.sent.add(reading.robot)
                log.info(
                    "%s: battery at %.0f %%, sent to its dock",
                    reading.robot,
                    100 * battery.percentage,
                )
        elif reading.topic == "dock_state":
            state: Any = reading.value  # mylab/msg/DockState
            if state.docked:
                log.info("%s: docked at %s", reading.robot, state.dock_id)

    def on_robot(self, robot: str, alive: bool) -> None:
        if not alive:
            self.sent.discard(robot)
