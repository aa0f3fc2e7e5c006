"""Apply each robot's profile to a built lab over time, on one thread, recording every change in
the lab's timeline."""

from __future__ import annotations

import random
import threading
import time
from collections.abc import Mapping

from arpz.lab.names import LabError
from arpz.lab.net import Lab
from arpz.lab.profiles import Profile, Step, schedule

#: how far ahead a profile is drawn when the run has no set end
DEFAULT_HORIZON_S = 3600.0


class ProfileRunner:
    """``start()`` applies every profile's state at 0 s at once (so the caller knows the links
    are set when it returns) and the later changes on a thread at their times, from the
    timeline's restarted clock; ``stop()`` ends the thread and raises LabError if a change
    failed meanwhile (each failure is also an ``error`` line of the timeline)."""

    def __init__(
        self,
        lab: Lab,
        profiles: Mapping[str, Profile],
        *,
        seed: int = 0,
        horizon_s: float = DEFAULT_HORIZON_S,
    ) -> None:
        for robot in profiles:
            lab.robot(robot)  # LabError for a robot the lab does not have
        self.lab = lab
        self.profiles = dict(profiles)
        steps = [
            (step.at_s, robot, step)
            for robot, profile in self.profiles.items()
            for step in schedule(profile, horizon_s, random.Random(f"{seed}:{robot}"))
        ]
        steps.sort(key=lambda item: (item[0], item[1]))
        self.steps: list[tuple[float, str, Step]] = steps
        self.errors: list[str] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._start = 0.0

    @property
    def elapsed_s(self) -> float:
        return time.monotonic() - self._start if self._start else 0.0

    def start(self) -> None:
        timeline = self.lab.timeline
        timeline.restart_clock()
        self._start = timeline.start_mono
        for robot, profile in self.profiles.items():
            timeline.record("profile", robot, profile=profile.name, description=profile.description)
        later = [item for item in self.steps if item[0] > 0]
        for _, robot, step in (item for item in self.steps if item[0] <= 0):
            self.lab.apply(robot, step.state, step.cause)
        self._thread = threading.Thread(
            target=self._run, args=(later,), name="arpz-lab-profiles", daemon=True
        )
        self._thread.start()

    def _run(self, steps: list[tuple[float, str, Step]]) -> None:
        for at_s, robot, step in steps:
            if self._stop.wait(max(0.0, self._start + at_s - time.monotonic())):
                return
            try:
                self.lab.apply(robot, step.state, step.cause)
            except LabError as exc:
                self.errors.append(str(exc))
                self.lab.timeline.record("error", robot, message=str(exc), cause=step.cause)

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=30)
        if self.errors:
            raise LabError(f"{len(self.errors)} link change(s) failed: {self.errors[0]}")
