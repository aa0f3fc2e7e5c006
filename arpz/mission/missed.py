"""What a robot that heard no commands did, from its acknowledgements: the planner's dead
reckoning per robot (issue 39).

A robot whose commands stop arriving drives on the last one it got until its watchdog stops it
(``command_timeout_s``, 0.5 s), while the others do what the planner sends them. The planner
learns it from the reliable channel's acknowledgements: commands it sent from ``since_s`` on
are not acknowledged (``HallwayPlanner.on_command_ack``). Once the robot acknowledges again,
this module says how far its heading went from the plan's: what it drove (the last command it
acknowledged, from ``since_s`` to its watchdog or until it heard again) less what it was sent
meanwhile. The planner turns it back by that much (``CatchUp``), so that a robot that missed
the start or the end of a turn is not left turned against the others, which planning on the
others' readings alone cannot see until a corridor later (docs/simulation.md, "Commands
acknowledged").

Only a robot whose readings kept arriving on time meanwhile (``fresh``: the planner asks for
readings no older than its acknowledgement slack) is reckoned: it was alive and sensing, so it
drove as its watchdog lets it, and what it sends was not held up, so its acknowledgements were
not either (over TCP a stall of the robot's uplink delays both alike). A frozen process sends
nothing and does not move, and a link dead both ways looks the same from here; those are left
to the formation rule, which measures.
Nor is a stretch in which the planner's own ticks came late (a starved CEDDP: the
acknowledgements were not read either), nor one made of commands sent before the robot was last
known to hear (their acknowledgements are catching up).
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass

#: ticks of commands kept per robot: enough to reckon from the first command not acknowledged
#: once the acknowledgements are ``slack_s`` late
LOG_TICKS = 256


@dataclass(frozen=True)
class Missed:
    """One stretch a robot heard no commands, and what it did to its heading."""

    robot: str
    #: when the first command it did not acknowledge was sent
    since_s: float
    #: when its acknowledgements came back
    heard_s: float
    #: the turn rate it drove on meanwhile (the last command it acknowledged), until its watchdog
    drove_rad_s: float
    #: its heading now less the plan's (rad, positive: turned left of it)
    error_rad: float


@dataclass
class _Deaf:
    since_s: float
    drove_rad_s: float
    #: the turn the planner sent it since ``since_s`` (rad), up to the last tick
    sent_rad: float
    #: its readings stayed fresh: it was alive and driving on its last command
    sure: bool


class MissedCommands:
    """Per robot, the turn rates sent at each tick and the stretches it did not acknowledge.

    Call ``update`` at every tick before deciding (it returns the stretches that just ended,
    reckoned), then ``sent`` with what this tick sends. Times are on the planner's clock."""

    def __init__(self, robots: tuple[str, ...], *, slack_s: float, timeout_s: float) -> None:
        self.slack_s = slack_s
        self.timeout_s = timeout_s
        self._log: dict[str, deque[tuple[float, float]]] = {
            robot: deque(maxlen=LOG_TICKS) for robot in robots
        }
        self._deaf: dict[str, _Deaf] = {}
        self._last_s: float | None = None
        #: per robot, when its last reckoned stretch ended (it heard again)
        self._heard_s: dict[str, float] = {}

    def deaf(self, robot: str) -> bool:
        """The robot has not acknowledged commands for longer than ``slack_s``."""
        return robot in self._deaf

    def sent(self, now_s: float, omegas: Mapping[str, float]) -> None:
        """This tick sends each robot the turn rate in ``omegas``."""
        for robot, omega_rad_s in omegas.items():
            if robot in self._log:
                self._log[robot].append((now_s, omega_rad_s))
        self._last_s = now_s

    def update(
        self,
        now_s: float,
        unacked_since: Mapping[str, float],
        fresh: Callable[[str], bool],
    ) -> list[Missed]:
        """Start or go on reckoning every robot that has not acknowledged the commands sent
        from ``unacked_since[robot]`` for more than ``slack_s``; return those that
        acknowledged again (with ``sure`` readings throughout: ``fresh(robot)`` each tick)."""
        ended: list[Missed] = []
        late = self._last_s is not None and now_s - self._last_s > self.slack_s
        for robot, log in self._log.items():
            deaf = self._deaf.get(robot)
            since_s = unacked_since.get(robot)
            if deaf is not None:
                if self._last_s is not None and log:
                    deaf.sent_rad += log[-1][1] * (now_s - self._last_s)
                deaf.sure = deaf.sure and fresh(robot) and not late
                if since_s is None or since_s > deaf.since_s + 1e-6:
                    del self._deaf[robot]
                    self._heard_s[robot] = now_s
                    if deaf.sure:
                        ended.append(self._reckon(robot, deaf, now_s))
                    deaf = None
            if (
                deaf is None
                and since_s is not None
                and now_s - since_s > self.slack_s
                and since_s >= self._heard_s.get(robot, -math.inf)
            ):
                self._deaf[robot] = self._start(log, since_s, now_s, fresh(robot) and not late)
        return ended

    def _start(
        self, log: deque[tuple[float, float]], since_s: float, now_s: float, sure: bool
    ) -> _Deaf:
        """From the log: the last turn rate it acknowledged (sent before ``since_s``: ticks are
        at least half a tick apart from it, whichever clock stamped the acknowledgement) and
        the turn it was sent from then to now."""
        entries = list(log)
        times = [t_s for t_s, _ in entries[-9:]]
        gaps = sorted(b - a for a, b in itertools.pairwise(times))
        half_tick_s = 0.5 * gaps[len(gaps) // 2] if gaps else 0.0  # the median: a usual tick
        drove = 0.0
        sent_rad = 0.0
        for index, (t_s, omega_rad_s) in enumerate(entries):
            if t_s < since_s - half_tick_s:
                drove = omega_rad_s
                continue
            until_s = entries[index + 1][0] if index + 1 < len(entries) else now_s
            sure = sure and until_s - t_s <= self.slack_s  # the planner's ticks were on time
            sent_rad += omega_rad_s * (until_s - t_s)
        return _Deaf(since_s, drove, sent_rad, sure)

    def _reckon(self, robot: str, deaf: _Deaf, now_s: float) -> Missed:
        drove_s = max(0.0, min(now_s, deaf.since_s + self.timeout_s) - deaf.since_s)
        error_rad = deaf.drove_rad_s * drove_s - deaf.sent_rad
        return Missed(robot, deaf.since_s, now_s, deaf.drove_rad_s, error_rad)


class CatchUp:
    """Turn rates added to bring robots back to the plan's heading: each robot's ``owed``
    heading (rad, positive: it must turn left) at up to ``rate_rad_s``, settled tick by tick
    by what was actually added."""

    def __init__(self, rate_rad_s: float, *, time_constant_s: float = 0.25) -> None:
        self.rate_rad_s = rate_rad_s
        self.time_constant_s = time_constant_s
        self.owed: dict[str, float] = {}
        self._adding: dict[str, float] = {}

    def owe(self, robot: str, rad: float) -> None:
        self.owed[robot] = self.owed.get(robot, 0.0) + rad

    def settle(self, elapsed_s: float) -> None:
        """The turn rates added at the last tick were driven for ``elapsed_s``."""
        for robot, adding in self._adding.items():
            left = self.owed.get(robot, 0.0) - adding * elapsed_s
            if abs(left) < 0.005 or math.copysign(1.0, left) != math.copysign(1.0, adding):
                self.owed.pop(robot, None)
            else:
                self.owed[robot] = left
        self._adding = {}

    def add(self, robot: str, omega_rad_s: float, limit_rad_s: float) -> float:
        """``omega_rad_s`` with this robot's catch-up added (within +-``limit_rad_s``)."""
        owed = self.owed.get(robot)
        if owed is None:
            return omega_rad_s
        wanted = min(max(owed / self.time_constant_s, -self.rate_rad_s), self.rate_rad_s)
        total = min(max(omega_rad_s + wanted, -limit_rad_s), limit_rad_s)
        self._adding[robot] = total - omega_rad_s
        return total
