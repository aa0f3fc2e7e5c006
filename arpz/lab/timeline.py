"""The lab's timeline: every change it makes to a link, with when it happened, as JSON lines.

Each line is one event: ``t`` (seconds from the timeline's start), ``mono`` (``time.monotonic()``,
the same clock in every process of the machine, so a test compares it with its own) and
``wall`` (``time.time()``), ``event`` (``lab_up``, ``profile``, ``link``, ``lab_down``, ``error``),
``robot`` when it concerns one, and the event's fields: for ``link`` the whole ``LinkState``
applied (``loss_up_pct``, ``loss_down_pct``, ``dead``, ``rate_kbit``, ``subnet``), the robot's
``address`` and the ``cause``. ``spans`` answers "the dead zone was from t=a to t=b".
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

from arpz.lab.profiles import LinkState

#: the file name beside the CEDDP's summary.json
TIMELINE_FILE = "lab_timeline.jsonl"

Entry = dict[str, Any]


class Timeline:
    """Appends events to ``path`` (flushed per line, so a killed run leaves what happened) and
    keeps them in ``entries``. Thread-safe. ``on_event`` (e.g. a progress printer) sees each."""

    def __init__(
        self, path: Path | None = None, on_event: Callable[[Entry], None] | None = None
    ) -> None:
        self.path = path
        self.on_event = on_event
        self.entries: list[Entry] = []
        self.start_mono = time.monotonic()
        self._lock = threading.Lock()
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text("", encoding="utf-8")

    def restart_clock(self) -> None:
        """``t`` counts from now (the profiles' start: the fleet is up)."""
        self.start_mono = time.monotonic()

    def record(self, event: str, robot: str | None = None, **fields: Any) -> Entry:
        mono = time.monotonic()
        entry: Entry = {
            "t": round(mono - self.start_mono, 4),
            "mono": mono,
            "wall": time.time(),
            "event": event,
        }
        if robot is not None:
            entry["robot"] = robot
        entry.update(fields)
        with self._lock:
            self.entries.append(entry)
            if self.path is not None:
                with self.path.open("a", encoding="utf-8") as out:
                    out.write(json.dumps(entry, sort_keys=True) + "\n")
        if self.on_event is not None:
            self.on_event(entry)
        return entry

    def link(self, robot: str, state: LinkState, cause: str, address: str) -> Entry:
        return self.record("link", robot, cause=cause, address=address, **asdict(state))


def load(path: Path) -> list[Entry]:
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines() if line]


def state_of(entry: Entry) -> LinkState:
    """The ``LinkState`` a ``link`` entry applied."""
    return LinkState(**{name: entry[name] for name in LinkState.__dataclass_fields__})


def link_states(entries: list[Entry], robot: str) -> list[tuple[float, LinkState]]:
    """The states applied to ``robot``'s link, in order, with their ``t``."""
    return [
        (e["t"], state_of(e)) for e in entries if e["event"] == "link" and e.get("robot") == robot
    ]


def spans(
    entries: list[Entry], robot: str, when: Callable[[LinkState], bool], *, clock: str = "t"
) -> list[tuple[float, float | None]]:
    """The intervals during which ``when(state)`` held on ``robot``'s link, in ``clock``
    (``t``, ``mono`` or ``wall``); an interval still open at the end has None as its end.
    ``spans(entries, "robot1", lambda s: s.dead)``: the dead zones."""
    found: list[tuple[float, float | None]] = []
    start: float | None = None
    for entry in entries:
        if entry["event"] != "link" or entry.get("robot") != robot:
            continue
        if when(state_of(entry)):
            if start is None:
                start = entry[clock]
        elif start is not None:
            found.append((start, entry[clock]))
            start = None
    if start is not None:
        found.append((start, None))
    return found
