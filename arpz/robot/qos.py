"""How a robot decides whether it can honour a QoS assignment from the CEDDP.

Pure logic. The robot refuses (and keeps what it runs) when a sensor cannot be read at the
assigned rate (its ``max_rate_hz``) or the assignment is malformed; otherwise it applies R to
every sensor, the assigned deadline, D as the writer depth and, when the assignment gives one,
the writers' heartbeat period (the closed loop's, from the measured link). A per-topic assignment
(``mode = "per_topic"``) gives each sensor its own R, deadline and D; a sensor it does not name
keeps the robot's fleet-wide entry.

**No sensor runs faster than its configured ``rate_hz``**: an assignment lowers a sensor's rate,
never raises it (a 5 Hz camera on a thin link was assigned 30.25 Hz, issue 39). A sensor whose
configured rate is below R runs at its own rate, its deadline stretched alike.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import msgspec

from arpz.core.config import SensorConfig
from arpz.core.messages import QosAssignmentMsg, RobotQos


@dataclass(frozen=True)
class QosDecision:
    applies: bool
    reason: str
    qos: RobotQos | None
    #: per sensor topic, when the assignment gives topics their own QoS
    per_topic: dict[str, RobotQos] = field(default_factory=dict)

    def for_topic(self, topic: str) -> RobotQos | None:
        """The QoS this sensor must run at: its own entry, else the robot's."""
        return self.per_topic.get(topic, self.qos)


#: the shortest heartbeat period a robot accepts: shorter would have its writers do little but
#: heartbeat (the CEDDP's loop never asks for less than ``heartbeat_min_ms``, 20 ms by default)
MIN_HEARTBEAT_S = 0.001


def _well_formed(qos: RobotQos) -> bool:
    heartbeat = qos.heartbeat_period_s
    return (
        qos.rate_hz > 0
        and qos.depth >= 1
        and qos.deadline_s > 0
        and (heartbeat is None or (math.isfinite(heartbeat) and heartbeat >= MIN_HEARTBEAT_S))
    )


def capped(qos: RobotQos, rate_hz: float) -> RobotQos:
    """``qos`` at no more than ``rate_hz`` (the sensor's configured rate), the deadline the same
    number of periods."""
    if qos.rate_hz <= rate_hz:
        return qos
    return msgspec.structs.replace(
        qos, rate_hz=rate_hz, deadline_s=qos.deadline_s * qos.rate_hz / rate_hz
    )


def decide(robot: str, message: QosAssignmentMsg, sensors: list[SensorConfig]) -> QosDecision:
    qos = message.robots.get(robot)
    if qos is None:
        return QosDecision(False, "not addressed to this robot", None)
    per_topic = dict(message.topics.get(robot, {})) if message.mode == "per_topic" else {}
    bad = [name for name, q in per_topic.items() if not _well_formed(q)]
    if not _well_formed(qos) or bad:
        what = f"topics {', '.join(sorted(bad))}" if bad else str(qos)
        return QosDecision(False, f"malformed assignment {what}", None)
    for s in sensors:
        own = per_topic.get(s.name, qos)
        if own.rate_hz > s.rate_hz:
            per_topic[s.name] = capped(own, s.rate_hz)
    too_slow = []
    for s in sensors:
        rate = per_topic.get(s.name, qos).rate_hz
        if s.max_rate_hz is not None and s.max_rate_hz < rate:
            too_slow.append(f"{s.name} (max {s.max_rate_hz:g} Hz) at {rate:.2f} Hz")
    if too_slow:
        return QosDecision(
            False,
            f"cannot run {', '.join(too_slow)}: the sensor cannot be read that fast",
            qos,
        )
    return QosDecision(True, "", qos, per_topic)
