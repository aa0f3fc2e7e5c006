"""Actuation: commands from the CEDDP reach an ``Actuator``.

The agent decodes commands on its own worker thread (never on a Zenoh callback) and hands each
one to ``Actuator.apply``. ``RecordingActuator`` is the simulated actuator: it keeps the last
command per name and counts them, which is what tests and the demo look at. A real robot
subclasses ``Actuator`` and drives its motors in ``apply``.
"""

from __future__ import annotations

import threading
from collections import Counter

from arpz.messages import Command


class Actuator:
    def apply(self, name: str, command: Command) -> None:
        """Act on one command (``name`` is the command topic, e.g. "velocity")."""
        raise NotImplementedError

    def stop(self) -> None:
        """Bring the robot to a safe state; called when the agent stops."""


class RecordingActuator(Actuator):
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.counts: Counter[str] = Counter()
        self.last: dict[str, Command] = {}
        self.stopped = False

    def apply(self, name: str, command: Command) -> None:
        with self._lock:
            self.counts[name] += 1
            self.last[name] = command

    def stop(self) -> None:
        self.stopped = True
