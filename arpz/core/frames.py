"""What the CEDDP shows, as plain data: the frames its dashboard logs (metrics per interval,
fleet events, a mission's world map) and the port the server hands them to.

The server builds these and never imports Rerun; ``arpz.ceddp.dashboard.Dashboard`` (the only
module that imports rerun) turns them into Rerun entities on a thread of its own.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import msgspec

#: metric name -> (view title, unit) for every per-topic series
TOPIC_METRICS: dict[str, str] = {
    "rate_hz": "arrival rate (Hz)",
    "bytes_per_s": "bytes/s",
    "latency_ms_p50": "latency p50 (ms, on the CEDDP's clock: robot clock offset corrected)",
    "latency_ms_p99": "latency p99 (ms, on the CEDDP's clock: robot clock offset corrected)",
    "lost": "lost (cumulative)",
    "held_back": "held back by local cache (cumulative)",
    "cc_discarded": "discarded by cache control (cumulative)",
    "decode_errors": "decode errors (cumulative)",
    "staleness_ms_p99": "staleness p99 (ms): CEDDP value older than the robot's reading",
}
#: metric name -> view title for every per-robot series
ROBOT_METRICS: dict[str, str] = {
    "hello_rtt_ms_p50": "Hello round trip p50 (ms)",
    "cpu_percent": "CPU (% of one core)",
    "qos_rate_hz": "QoS rate R applied (Hz)",
    "qos_depth": "QoS depth D applied (samples)",
    "downlink_written": "commands and Hello hops written to the robot (cumulative)",
    "downlink_lost": "downlink lost or expired, robot-reported (cumulative)",
    "watchdog_stops": "command watchdog safe stops (cumulative)",
    "refused": "samples refused: INCOMPATIBLE_QOS (cumulative)",
    "ingest_load": "CEDDP ingest load (share of time not waiting for samples)",
    "ingest_backlog_ms": "CEDDP ingest backlog (ms the oldest waiting sample waited)",
    "capacity_hz": "CEDDP measured capacity (samples per busy second)",
    "budget_hz": "fleet rate budget of the overload governor (samples/s)",
    "clock_offset_ms": "clock offset to the CEDDP (ms, CEDDP - robot; latencies corrected by it)",
    "clock_delay_ms": "clock exchange round trip (ms; the offset is right within half of it)",
    "clock_over_bound": "clock offset beyond [clock] max_offset_ms (1 = flagged)",
}
TIMELINE = "time"


@dataclass(frozen=True)
class MetricsFrame:
    """One reporting interval: ``topics[(robot, topic)][metric]`` and ``robots[robot][metric]``."""

    stamp_ns: int
    topics: dict[tuple[str, str], dict[str, float]] = field(default_factory=dict)
    robots: dict[str, dict[str, float]] = field(default_factory=dict)


@dataclass(frozen=True)
class WorldMap:
    """The static world of a mission: wall polylines and obstacle outlines."""

    stamp_ns: int
    walls: list[list[tuple[float, float]]]
    obstacles: list[list[tuple[float, float]]]


@dataclass(frozen=True)
class Event:
    stamp_ns: int
    text: str
    level: str = "INFO"


class WorldView(msgspec.Struct, frozen=True):
    """What the dashboard draws of the world at one moment."""

    stamp_ns: int
    #: robot -> (x_m, y_m, theta_rad), the true pose
    poses: dict[str, tuple[float, float, float]]
    #: robot -> end points of its 8 rays, cast from the true pose with the ranges the CEDDP has
    rays: dict[str, list[tuple[float, float]]]
    #: robot -> the true path so far
    paths: dict[str, list[tuple[float, float]]]


class DashboardLike(Protocol):
    """Where the server submits frames; ``submit`` never blocks (False: dropped and counted)."""

    dropped: int
    #: metric rows not logged (not a number, or refused by the recorder), counted not silent
    rows_refused: int

    def submit(self, item: MetricsFrame | WorldMap | WorldView | Event) -> bool: ...
    def close(self) -> None: ...
