"""A robot whose clock is shifted, and the CEDDP, over the in-memory transport: the offset
reaches the dashboard's frames, CeddpStats and the summary, and the latency is corrected."""

from __future__ import annotations

import threading

import msgspec
import pytest

from arpz.ceddp.server import CeddpServer
from arpz.core import keys
from arpz.core.config import CeddpConfig, ConfigError, RobotClockConfig, RobotConfig, from_dict
from arpz.core.frames import Event, MetricsFrame, WorldMap, WorldView
from arpz.core.messages import CEDDP_STATS_DECODER, CeddpStats
from arpz.robot.agent import RobotAgent
from arpz.transport.memory import MemoryBus, MemoryTransport
from tests.support import wait_until


class Frames:
    """A dashboard that keeps what it is given."""

    dropped = 0
    rows_refused = 0

    def __init__(self) -> None:
        self.items: list[MetricsFrame | WorldMap | WorldView | Event] = []
        self.lock = threading.Lock()

    def submit(self, item: MetricsFrame | WorldMap | WorldView | Event) -> bool:
        with self.lock:
            self.items.append(item)
        return True

    def close(self) -> None:
        pass

    def robot_rows(self, robot: str) -> list[dict[str, float]]:
        with self.lock:
            return [
                i.robots[robot]
                for i in self.items
                if isinstance(i, MetricsFrame) and robot in i.robots
            ]


def test_a_shifted_robot_in_frames_ceddp_stats_and_summary() -> None:
    bus = MemoryBus()
    frames = Frames()
    config = CeddpConfig(fleet="f", rrd="unused.rrd", metrics_period_s=0.05)
    server = CeddpServer(config, MemoryTransport(bus), dashboard=frames)
    reports: list[CeddpStats] = []
    MemoryTransport(bus).subscribe(
        keys.ceddp_stats_key("f"), lambda k, p, a: reports.append(CEDDP_STATS_DECODER.decode(p))
    )
    server.start()
    agent = RobotAgent(
        RobotConfig(
            robot_id="r1",
            fleet="f",
            preset="machine1",
            preset_rate_hz=100,
            stats_period_s=0.05,
            clock=RobotClockConfig(shift_s=2.0, period_s=0.1),
        ),
        MemoryTransport(bus),
    )
    stop = threading.Event()
    agent.start()
    thread = threading.Thread(target=agent.run, args=(stop,))
    thread.start()
    try:
        wait_until(
            lambda: (
                any("clock_offset_ms" in row for row in frames.robot_rows("r1"))
                and any(r.clock_flagged for r in reports)
            ),
            what="the offset in a frame and the flag in CeddpStats",
        )
    finally:
        stop.set()
        thread.join(5)
        agent.shutdown()
    summary = server.shutdown()
    row = next(r for r in frames.robot_rows("r1") if "clock_offset_ms" in r)
    assert abs(row["clock_offset_ms"] + 2000) < 50 and row["clock_over_bound"] == 1.0
    assert row["clock_delay_ms"] >= 0
    last = reports[-1]
    assert (
        last.clock_corrected and last.clock_max_offset_ms == 50.0 and last.clock_flagged == ["r1"]
    )
    assert last.arpz_version and last.zenoh_version and last.access_control is False
    robot = summary["robots"]["r1"]
    assert robot["clock_corrected"] and robot["clock"]["over_bound"]
    assert robot["clock"]["uncorrected_samples"] == 0
    assert -1 < robot["latency_ms_p50"] < 50  # 2 000 ms off without the correction
    assert summary["clock"]["flagged"] == ["r1"]


@pytest.mark.parametrize(
    ("kind", "clock", "field"),
    [
        (RobotConfig, {"period_s": 0}, "period_s must be > 0"),
        (RobotConfig, {"burst": 0}, "burst must be >= 1"),
        (RobotConfig, {"shfit_s": 1}, "shfit_s"),
        (CeddpConfig, {"max_offset_ms": -1}, "max_offset_ms must be > 0"),
    ],
)
def test_clock_settings_are_checked_and_named(
    kind: type[msgspec.Struct], clock: dict[str, object], field: str
) -> None:
    raw: dict[str, object] = {"clock": clock}
    if kind is RobotConfig:
        raw["robot_id"] = "r1"
    with pytest.raises(ConfigError, match=rf"x.toml: field 'clock.*{field}"):
        from_dict(raw, kind, source="x.toml")
