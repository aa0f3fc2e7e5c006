"""The pure parts of the hallway mission's ROS 2 nodes (``mission_node``): pacing, the command
acknowledgement bookkeeping, the yaw of a pose message, a process's CPU time and the verdict's
letter. No rclpy here, so they are tested without ROS 2 installed.
"""

from __future__ import annotations

import math
from typing import Any

#: the LIDAR beams per robot (seed 001 section 3.2) plus its command and telemetry topics: T_a
#: of eq. 1 as arpz's simulated robots announce it (arpz.experiment.fleet.topic_counts)
MISSION_TOPICS_PER_ROBOT = 8 + 2


class Pacer:
    """A periodic job in a loop that polls it: ``due(now_s)`` is True once per period.

    A loop that falls more than ``max_behind`` periods behind (a busy core) skips the missed
    periods instead of bursting to catch up, and counts them in ``skipped``, as a sensor that
    samples at its rate, not a queue that replays the past.
    """

    def __init__(self, rate_hz: float, start_s: float, *, max_behind: int = 1) -> None:
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
        self.period_s = 1.0 / rate_hz
        self.next_s = start_s
        self.max_behind = max_behind
        self.skipped = 0

    def due(self, now_s: float) -> bool:
        if now_s < self.next_s:
            return False
        behind = int((now_s - self.next_s) / self.period_s)
        if behind > self.max_behind:
            self.skipped += behind
            self.next_s += behind * self.period_s
        self.next_s += self.period_s
        return True


class AckTracker:
    """When the oldest command not yet acknowledged by one robot was sent, from polls of
    "every command acknowledged?" (rclpy's ``Publisher.wait_for_all_acked`` with no wait: the
    DDS reliable writer's own acknowledgements, as arpz's CEDDP reads its channel's).

    At each tick: ``poll(all_acked)`` before sending, give ``unacknowledged_since_s`` to
    ``HallwayPlanner.on_command_ack``, then ``sent(now_s)``. A poll that finds everything
    acknowledged clears it; otherwise the first command sent after the last clear is the
    oldest one still unacknowledged (what ``arpz.mission.offline`` models too).
    """

    def __init__(self) -> None:
        self.unacknowledged_since_s: float | None = None
        self.polls = 0
        self.unacknowledged_polls = 0

    def poll(self, all_acked: bool) -> float | None:
        self.polls += 1
        if all_acked:
            self.unacknowledged_since_s = None
        else:
            self.unacknowledged_polls += 1
        return self.unacknowledged_since_s

    def sent(self, now_s: float) -> None:
        if self.unacknowledged_since_s is None:
            self.unacknowledged_since_s = now_s


def yaw_quaternion(theta_rad: float) -> tuple[float, float]:
    """(z, w) of the quaternion of a rotation by ``theta_rad`` about z (x = y = 0)."""
    return (math.sin(theta_rad / 2.0), math.cos(theta_rad / 2.0))


def yaw_of(z: float, w: float) -> float:
    """The inverse of ``yaw_quaternion``, in (-pi, pi]."""
    return math.atan2(2.0 * w * z, 1.0 - 2.0 * z * z)


def verdict_letter(result: dict[str, Any] | None) -> str:
    """Figure 16's outcome of a mission result (``MissionResult`` as JSON): S success,
    T timeout, C collision, P a phantom-obstacle stop, N no verdict (never started or
    incomplete)."""
    if not result:
        return "N"
    if result.get("mission") == "success":
        return "S"
    failure = result.get("failure")
    if failure is None:
        reason = str(result.get("reason", ""))
        failure = reason.split(":", 1)[0].strip()
    return {"timeout": "T", "collision": "C", "phantom_obstacle": "P"}.get(str(failure), "N")
