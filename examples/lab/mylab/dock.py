"""The lab's planner: drives each robot slower as its battery drains (a Twist on cmd_vel), and
sends a robot whose battery falls under ``threshold`` to its dock by calling its "dock" service
(then stops driving it: its watchdog stops it)."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from concurrent.futures import Future
from typing import Any

from arpz.ceddp import Planner, Reading
from arpz.ceddp.services import ServiceError

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
                self.sent.add(reading.robot)
                # never wait in on_reading (it holds the CEDDP's ingest): the answer comes later
                call = self.robot_service_async(reading.robot, "dock", {}, timeout_s=5.0)
                call.add_done_callback(lambda done, robot=reading.robot: self._docking(robot, done))
                log.info(
                    "%s: battery at %.0f %%, sent to its dock",
                    reading.robot,
                    100 * battery.percentage,
                )
        elif reading.topic == "dock_state":
            state: Any = reading.value  # mylab/msg/DockState
            if state.docked:
                log.info("%s: docked at %s", reading.robot, state.dock_id)

    def _docking(self, robot: str, call: Future[Any]) -> None:
        try:
            answer = call.result()
        except ServiceError as exc:  # timeout, robot gone, handler failed...
            log.warning("%s: dock service: %s", robot, exc)
            self.sent.discard(robot)  # ask again at its next battery reading
            return
        log.info("%s: dock service says %s: %s", robot, answer.success, answer.message)

    def on_robot(self, robot: str, alive: bool) -> None:
        if not alive:
            self.sent.discard(robot)
