"""The lab's base: drives on "velocity" ([v, omega]) and goes to its dock on "dock"."""

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
    commands = ("velocity", "dock")

    def __init__(self, options: Mapping[str, Any]) -> None:
        super().__init__(options)
        self.dock_after_s = float(options.get("dock_after_s", 1.0))

    def apply(self, name: str, command: Command) -> None:
        if name == "velocity":
            with LOCK:
                BODY.speed_m_s = float(command.value[0])  # type: ignore[index]
        elif name == "dock" and command.value:
            with LOCK:
                if BODY.docked or BODY.docking:
                    return
                BODY.docking = True
            log.info("docking")
            threading.Timer(self.dock_after_s, self._docked).start()

    def _docked(self) -> None:
        with LOCK:
            BODY.docking, BODY.docked, BODY.speed_m_s = False, True, 0.0
        log.info("docked")

    def safe_stop(self) -> None:
        with LOCK:
            BODY.speed_m_s = 0.0
