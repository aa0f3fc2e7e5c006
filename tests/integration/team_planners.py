"""Planners a team would write, loaded by a real CEDDP from its TOML in the planner tests."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from arpz.ceddp.planner import Planner, Reading


class CountingPlanner(Planner):
    """Writes how many readings of each topic it saw, and whether it was attached and started,
    to ``options.out`` on every reading (the test reads the file back)."""

    def __init__(self, options: Mapping[str, Any]) -> None:
        super().__init__(options)
        self.out = Path(str(options["out"]))
        self.seen: dict[str, int] = {}
        self.started = False

    def start(self) -> None:
        self.started = True

    def on_reading(self, reading: Reading) -> None:
        key = f"{reading.robot}/{reading.topic}"
        self.seen[key] = self.seen.get(key, 0) + 1
        state = {"seen": self.seen, "started": self.started, "attached": self.commands is not None}
        partial = self.out.with_suffix(".partial")
        partial.write_text(json.dumps(state))
        partial.replace(self.out)


class RaisingPlanner(Planner):
    """Raises on every reading: the CEDDP must count it and go on."""

    def on_reading(self, reading: Reading) -> None:
        raise ZeroDivisionError(f"reading of {reading.topic} divided by zero")


class NeedsOptions(Planner):
    """Refuses to be made without its option (a bad [[planners]] entry)."""

    def __init__(self, options: Mapping[str, Any]) -> None:
        super().__init__(options)
        self.threshold = float(options["threshold"])
