"""What the CEDDPs say of themselves while the fleet load runs: their ``CeddpStats`` reports.

The load test reads them through the reliable channel, as any client may (one more reader of
the CEDDPs' report writers: negligible next to the fleet's). Fields a CEDDP does not publish
(an older ``CeddpStats``) stay None and the report says "unavailable".

Several CEDDPs of one mesh publish on the same key, and ``CeddpStats`` carries no server id: a
report is attributed by the robots of its topics (robot ``c{k}-...`` belongs to CEDDP k).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any

from arpz.channel.io import Inlet
from arpz.core import keys
from arpz.core.messages import CEDDP_STATS_DECODER, DECODE_ERRORS
from arpz.core.traffic import REPORT_QOS
from arpz.core.transport import SessionSettings
from arpz.transport.zenoh import ZenohTransport


@dataclass
class SelfReport:
    """The worst of what one CEDDP reported over the window."""

    reports: int = 0
    #: share of each interval its sensor path was busy (1.0: saturated), the highest seen
    load_max: float | None = None
    #: the last dashboard_dropped (a count since start)
    dashboard_dropped: int | None = None
    #: its own CPU figure (percent of one core), the highest interval seen
    cpu_percent_max: float | None = None
    #: its measured capacity (samples per busy second), the last seen
    capacity_hz: float | None = None
    #: the longest a sample waited in it before its sensor path took it (its ingest backlog
    #: in time), ms, the highest interval seen
    backlog_ms_max: float | None = None


def ceddp_of(topics: list[Any]) -> int | None:
    """CEDDP k from a report's topics (robot ``c{k}-r...``); None when there are none."""
    for rate in topics:
        head = str(rate.robot).split("-", 1)[0]
        if head.startswith("c") and head[1:].isdigit():
            return int(head[1:])
    return None


class CeddpWatcher:
    """Subscribes to ``arpz/{fleet}/ceddp/stats`` through one router of the mesh."""

    def __init__(
        self, fleet: str, endpoint: str, ceddps: int, zenoh_config: str | None = None
    ) -> None:
        self.reports = [SelfReport() for _ in range(ceddps)]
        self._lock = threading.Lock()
        self._single = ceddps == 1
        self._transport = ZenohTransport.open(
            SessionSettings(mode="client", connect=[endpoint], config_file=zenoh_config),
            timeout_s=10,
        )
        try:
            self._inlet = Inlet(
                self._transport, keys.ceddp_stats_key(fleet), REPORT_QOS, self._on_stats
            )
        except BaseException:
            self._transport.close()
            raise

    def _on_stats(self, key: str, payload: bytes) -> None:
        try:
            stats = CEDDP_STATS_DECODER.decode(payload)
        except DECODE_ERRORS:
            return
        index = 0 if self._single else ceddp_of(list(stats.topics))
        if index is None or index >= len(self.reports):
            return
        load = getattr(stats, "load", None)
        dropped = getattr(stats, "dashboard_dropped", None)
        capacity = getattr(stats, "capacity_hz", None)
        backlog = getattr(stats, "ingest_backlog_ms", None)
        with self._lock:
            r = self.reports[index]
            r.reports += 1
            if isinstance(load, float):
                r.load_max = load if r.load_max is None else max(r.load_max, load)
            if isinstance(dropped, int):
                r.dashboard_dropped = dropped
            if isinstance(capacity, float):
                r.capacity_hz = capacity
            if isinstance(backlog, (int, float)):
                r.backlog_ms_max = max(r.backlog_ms_max or 0.0, float(backlog))
            cpu = float(stats.cpu_percent)
            r.cpu_percent_max = cpu if r.cpu_percent_max is None else max(r.cpu_percent_max, cpu)

    def snapshot(self) -> list[SelfReport]:
        with self._lock:
            return [SelfReport(**vars(r)) for r in self.reports]

    def close(self) -> None:
        try:
            self._inlet.close()
        finally:
            self._transport.close()
