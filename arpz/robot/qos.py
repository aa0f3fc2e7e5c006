"""How a robot decides whether it can honour a QoS assignment from the CEDDP.

Pure logic. The robot refuses (and keeps what it runs) when a sensor cannot be read at the
assigned rate (its ``max_rate_hz``) or the assignment is malformed; otherwise it applies R to
every sensor, 1/R as the deadline and D as the writer depth.
"""

from __future__ import annotations

from dataclasses import dataclass

from arpz.config import SensorConfig
from arpz.messages import QosAssignmentMsg, RobotQos


@dataclass(frozen=True)
class QosDecision:
    applies: bool
    reason: str
    qos: RobotQos | None


def decide(robot: str, message: QosAssignmentMsg, sensors: list[SensorConfig]) -> QosDecision:
    qos = message.robots.get(robot)
    if qos is None:
        return QosDecision(False, "not addressed to this robot", None)
    if not (qos.rate_hz > 0 and qos.depth >= 1 and qos.deadline_s > 0):
        return QosDecision(False, f"malformed assignment {qos}", None)
    too_slow = [
        f"{s.name} (max {s.max_rate_hz:g} Hz)"
        for s in sensors
        if s.max_rate_hz is not None and s.max_rate_hz < qos.rate_hz
    ]
    if too_slow:
        return QosDecision(
            False,
            f"cannot run at {qos.rate_hz:.2f} Hz: {', '.join(too_slow)} cannot be read that fast",
            qos,
        )
    return QosDecision(True, "", qos)
