"""The robot's own summary (``python -m arpz.robot --summary-json PATH``).

The CEDDP's ``summary.json`` reconciles what it received against what each robot reported; a
robot that could not reach the CEDDP at the end (a dead zone, a roam it did not come back from)
never had its last counts reported. Its own summary keeps them: its final report (``RobotStats``:
per topic produced, sent, held back, write failures...; per CEDDP -> robot key the downlink's
counters; its incarnation), and its link's history (each drop with its cause and durations,
``arpz.robot.link_monitor``). Written atomically (a temporary file renamed over the path), at
exit with ``"complete": true`` and, while running, after each drop and each reconnection with
``"complete": false``.
"""

from __future__ import annotations

import json
import os
import tempfile
import threading
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import msgspec

from arpz.robot.agent import RobotAgent
from arpz.robot.link_monitor import LinkWatch


def _iso(unix_s: float) -> str:
    return datetime.fromtimestamp(unix_s, UTC).isoformat(timespec="milliseconds")


class RobotSummary:
    """Writes one robot's summary to ``path`` (thread-safe: the link's thread writes it after a
    drop or a reconnection, the main thread at exit)."""

    def __init__(self, path: Path, agent: RobotAgent, watch: LinkWatch | None = None) -> None:
        self.path = path
        self.agent = agent
        self.watch = watch
        self.started_at = time.time()
        self._lock = threading.Lock()

    def build(self, *, complete: bool) -> dict[str, Any]:
        agent = self.agent
        stats = agent.final_stats if complete and agent.final_stats is not None else None
        if stats is None:
            stats = agent.stats(final=False, rates=False)
        now = time.time()
        link: dict[str, Any] = (
            self.watch.monitor.summary() if self.watch is not None else {"watched": False}
        )
        for event in link.get("events", []):
            for field in ("lost_at", "back_at"):
                if event.get(field) is not None:
                    event[f"{field}_iso"] = _iso(event[field])
        summary: dict[str, Any] = {
            "complete": complete,
            "fleet": agent.config.fleet,
            "started_at": _iso(self.started_at),
            "written_at": _iso(now),
            "duration_s": round(now - self.started_at, 3),
            # the CEDDP acknowledged the final report (None: none sent yet)
            "final_report_acknowledged": agent.final_acknowledged,
            **msgspec.to_builtins(stats),
            "link": link,
        }
        return summary

    def write(self, *, complete: bool) -> None:
        """Build and write the summary atomically (a reader never sees half a file)."""
        with self._lock:
            text = json.dumps(self.build(complete=complete), indent=1, sort_keys=True)
            directory = self.path.parent
            directory.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", dir=directory)
            try:
                with os.fdopen(fd, "w") as out:
                    out.write(text + "\n")
                os.replace(tmp, self.path)
            except BaseException:
                Path(tmp).unlink(missing_ok=True)
                raise
