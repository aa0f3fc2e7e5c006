"""The simulated robot's body, shared by this lab's drivers and actuator in one robot process
(a real robot reads its devices instead)."""

from __future__ import annotations

import threading
from dataclasses import dataclass


@dataclass
class Body:
    docked: bool = False
    docking: bool = False
    speed_m_s: float = 0.0


BODY = Body()
LOCK = threading.Lock()
