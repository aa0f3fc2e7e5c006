"""The lab's base: drives on "cmd_vel" (a geometry_msgs/msg/Twist, as on a ROS 2 robot), and goes
to its dock when its "dock" service (std_srvs/srv/Trigger) is called."""

from __future__ import annotations

import logging
import threading
from collections.abc import Mapping
from typing import Any

from arpz.core.messages import Command
from arpz.robot import Actuator
from mylab.state import BODY, LOCK

log = logging.getLogger(__name__)


class Base(Actuator):
    commands = ("cmd_vel",)

    def __init__(self, options: Mapping[str, Any]) -> None:
        super().__init__(options)
        self.command_types = {"cmd_vel": "geometry_msgs/msg/Twist"}
        self.dock_after_s = float(options.get("dock_after_s", 1.0))

    def apply(self, name: str, command: Command) -> None:
        if name == "cmd_vel":
            twist: Any = command.value  # the message: geometry_msgs/msg/Twist
            with LOCK:
                changed = BODY.speed_m_s != twist.linear.x
                BODY.speed_m_s = twist.linear.x
            if changed:
                log.info("driving at %.2f m/s", twist.linear.x)

    def safe_stop(self) -> None:
        """No cmd_vel within its watchdog deadline ([watchdog] in robot.toml): stop."""
        with LOCK:
            moving, BODY.speed_m_s = BODY.speed_m_s != 0.0, 0.0
        if moving:
            log.info("safe stop: no cmd_vel within its deadline: stopped")


def dock(request: Any) -> dict[str, object]:
    """The "dock" service (std_srvs/srv/Trigger, robot.toml's [[services]]): start docking, or
    say why not. It runs on the service's own worker thread, so it shares BODY under LOCK."""
    with LOCK:
        if BODY.docked or BODY.docking:
            return {"success": False, "message": "already docked" if BODY.docked else "docking"}
        BODY.docking = True
    log.info("docking")
    threading.Timer(1.0, _docked).start()
    return {"success": True, "message": "docking at dock-1"}


def _docked() -> None:
    with LOCK:
        BODY.docking, BODY.docked, BODY.speed_m_s = False, True, 0.0
    log.info("docked")
