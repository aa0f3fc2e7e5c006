"""The vocabulary shared by the hallway planner (CEDDP side) and the judge: commands and events.

Both are msgspec Structs so the integrator can send them over Zenoh (commands to actuation,
events to the dashboard and the judge) without another set of types.
"""

from __future__ import annotations

from typing import Final, Literal

import msgspec


class VelocityCommand(msgspec.Struct, frozen=True, array_like=True):
    """Forward speed and turn rate (counter-clockwise positive) for one robot."""

    v_m_s: float
    omega_rad_s: float


STOP: Final = VelocityCommand(0.0, 0.0)

#: What the planner reports as the mission goes:
#: ``started`` the fleet first moves; ``turn_started``/``turn_done`` a corner; ``obstacle_stop``
#: and ``clear`` a follower saw something close ahead (or any robot something within its
#: clearance) and later saw it gone; ``stale_stop`` and ``resumed`` the data the planner needs got
#: too old, then fresh again (while held, ``stale_stop`` is repeated, at most once a second, when
#: another reading becomes the oldest); ``off_lane`` and ``in_lane`` a follower was seen out of
#: its lane or turned away from the leader's heading (its own side beams against the leader's)
#: and is steered back, then is back; ``missed_commands`` a robot acknowledged its commands
#: again after a stretch without (it drove on its last one), and is turned back to the plan's
#: heading; ``home`` the leader thinks it is home and the fleet stops.
EventKind = Literal[
    "started",
    "turn_started",
    "turn_done",
    "obstacle_stop",
    "clear",
    "stale_stop",
    "resumed",
    "off_lane",
    "in_lane",
    "missed_commands",
    "home",
]


class MissionEvent(msgspec.Struct, frozen=True, kw_only=True):
    """One planner decision, with the reading behind it so a failure can be explained."""

    t_s: float
    kind: EventKind
    robot: str
    text: str
    beam_deg: int | None = None
    range_m: float | None = None
    age_s: float | None = None
    corner: int | None = None
