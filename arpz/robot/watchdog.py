"""The robot's command watchdog: stop safely when commands stop arriving.

If the CEDDP dies or the link goes down, no new command arrives, and a robot must not keep
driving on its last velocity command. Each command name (e.g. "velocity") has a deadline, as
ROS 2's deadline QoS or a motor controller's cmd_vel timeout: when a deadline passes with no new
command for that name, the caller puts the robot in a safe stop (``Actuator.safe_stop``), and the
next command for that name ends it (the robot resumes).

Pure logic, as the local cache: no threads, no I/O, no clock. The caller passes ``now_s`` from a
monotonic clock, calls ``on_command`` for each command it applies and ``check`` on every tick of
its scheduler. Not thread-safe: call it from one thread, or hold a lock around each call.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TypedDict


class WatchdogSnapshot(TypedDict):
    """What ``CommandWatchdog.snapshot`` returns, for stats and reports (plain JSON types)."""

    stops: dict[str, int]
    stopped: list[str]


class CommandWatchdog:
    """Per command name, a deadline since the last command; each expiry reported once.

    A name is armed by its first command: a robot that never moved needs no stop. Once its
    deadline passes, ``check`` reports it once and the name stays in ``stopped`` (disarmed)
    until the next command for it re-arms it and ``on_command`` returns True ("resumed").
    Names without a configured deadline are never armed and never fire.
    """

    def __init__(self, deadlines_s: Mapping[str, float]) -> None:
        for name, deadline_s in deadlines_s.items():
            if not deadline_s > 0:  # NaN too
                raise ValueError(
                    f"watchdog deadline for command {name!r} must be > 0 seconds, "
                    f"got {deadline_s!r}"
                )
        self.deadlines_s: dict[str, float] = dict(deadlines_s)
        #: safe stops so far per configured name (0 for a name that never stopped)
        self.stops: dict[str, int] = dict.fromkeys(self.deadlines_s, 0)
        self.total_stops = 0
        #: names in a safe stop now: their deadline passed and no command has come since
        self.stopped: set[str] = set()
        #: ``now_s`` of the ``check`` that reported the latest stop, None before the first
        self.last_stop_s: float | None = None
        # name -> time of its last command, for armed names only
        self._armed: dict[str, float] = {}

    def on_command(self, name: str, now_s: float) -> bool:
        """A command for ``name`` arrived at ``now_s``: (re-)arm its deadline.

        Returns True if this command ends a safe stop for ``name`` (the robot resumes), so the
        caller can log it. A name without a deadline is ignored and returns False.
        """
        if name not in self.deadlines_s:
            return False
        self._armed[name] = now_s
        if name in self.stopped:
            self.stopped.discard(name)
            return True
        return False

    def check(self, now_s: float) -> list[str]:
        """Names whose deadline has passed since their last command, sorted; each reported once.

        A deadline passes at ``last command + deadline``, the time ``next_expiry_s`` returns.

        A reported name is disarmed and counted as a safe stop; the caller calls
        ``Actuator.safe_stop`` and logs it. It is reported again only after a new command.
        """
        expired = sorted(
            name for name, last_s in self._armed.items() if now_s >= last_s + self.deadlines_s[name]
        )
        for name in expired:
            del self._armed[name]
            self.stopped.add(name)
            self.stops[name] += 1
            self.total_stops += 1
            self.last_stop_s = now_s
        return expired

    def next_expiry_s(self) -> float | None:
        """When the earliest armed deadline passes (a caller may sleep until then and
        ``check``), or None when nothing is armed."""
        return min(
            (last_s + self.deadlines_s[name] for name, last_s in self._armed.items()),
            default=None,
        )

    def snapshot(self) -> WatchdogSnapshot:
        """The counters as plain types: ``{"stops": {name: n}, "stopped": [sorted names]}``."""
        return {"stops": dict(self.stops), "stopped": sorted(self.stopped)}
