"""The lab's sensor drivers: each returns a whole message of its ROS 2 type, as a dict of its
fields (arpz checks it against the type and stamps the header)."""

from __future__ import annotations

import math
from typing import Any

from arpz.robot import SensorDriver
from mylab.state import BODY, LOCK

#: sensor_msgs/msg/BatteryState's power_supply_status values
CHARGING, DISCHARGING = 1, 2


class Gps(SensorDriver):
    """A fix walking around the lab's origin (``options``: ``latitude``, ``longitude``)."""

    def __init__(self, options: dict[str, Any], seed: int) -> None:
        super().__init__(options, seed)
        self.latitude = float(options.get("latitude", 51.4545))
        self.longitude = float(options.get("longitude", -2.5879))

    def read(self, now_s: float) -> Any:
        with LOCK:
            moving = not BODY.docked
        drift = 1e-5 * math.sin(now_s / 5) if moving else 0.0
        return {
            "status": {"status": 0, "service": 1},
            "latitude": self.latitude + drift,
            "longitude": self.longitude + drift,
            "altitude": 11.0,
            "position_covariance": [0.0] * 9,
            "position_covariance_type": 0,
        }


class Battery(SensorDriver):
    """A battery that drains ``drain_per_s`` percent a second while off its dock and charges
    on it (``options``: ``start``, ``drain_per_s``)."""

    def __init__(self, options: dict[str, Any], seed: int) -> None:
        super().__init__(options, seed)
        self.percent = float(options.get("start", 100.0))
        self.drain_per_s = float(options.get("drain_per_s", 1.0))
        self.last_s = 0.0

    def read(self, now_s: float) -> Any:
        elapsed, self.last_s = now_s - self.last_s, now_s
        with LOCK:
            docked = BODY.docked
        rate = 5 * self.drain_per_s if docked else -self.drain_per_s
        self.percent = min(100.0, max(0.0, self.percent + rate * elapsed))
        return {
            "voltage": 11.1 + self.percent / 100,
            "temperature": 25.0,
            "current": 1.5 if docked else -0.8,
            "charge": math.nan,
            "capacity": math.nan,
            "design_capacity": 5.0,
            "percentage": self.percent / 100,
            "power_supply_status": CHARGING if docked else DISCHARGING,
            "power_supply_health": 1,
            "power_supply_technology": 3,
            "present": True,
            "cell_voltage": [],
            "cell_temperature": [],
            "location": "base",
            "serial_number": "lab-0001",
        }


class DockSensor(SensorDriver):
    """The lab's own type, mylab/msg/DockState (msg/mylab/msg/DockState.msg)."""

    def read(self, now_s: float) -> Any:
        with LOCK:
            docked, docking = BODY.docked, BODY.docking
        return {
            "docked": docked,
            "dock_id": "dock-1" if docked or docking else "",
            "distance_m": 0.0 if docked else 2.5,
        }
