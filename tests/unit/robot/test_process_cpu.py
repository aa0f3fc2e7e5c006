"""The robots of one process share one reading of its CPU time (arpz.robot.process_cpu)."""

from __future__ import annotations

import time

import pytest

from arpz.robot.process_cpu import ProcessCpu, cpu_percent


def test_a_reading_younger_than_the_interval_is_reused() -> None:
    reader = ProcessCpu(min_interval_s=60.0)
    first = reader.read()
    assert reader.read() is first  # asked again within the interval: no new system call


def test_an_older_reading_is_renewed() -> None:
    reader = ProcessCpu(min_interval_s=0.05)
    first = reader.read()
    deadline = time.monotonic() + 0.1
    while time.monotonic() < deadline:  # spend CPU, so the next reading differs
        pass
    second = reader.read()
    assert second is not first
    assert second[0] - first[0] >= 0.05
    assert second[1] > first[1]


def test_cpu_percent_between_two_readings() -> None:
    assert cpu_percent((10.0, 1.0), (10.5, 1.25)) == pytest.approx(50.0)
    assert cpu_percent((10.0, 1.0), (12.0, 5.0)) == pytest.approx(200.0)  # two cores busy


def test_the_same_reading_twice_gives_no_figure() -> None:
    """A robot asking within the interval keeps its previous figure (None here), never 0 %."""
    reading = (10.0, 1.0)
    assert cpu_percent(reading, reading) is None


def test_robot_stats_report_the_process_cpu() -> None:
    from arpz.core.config import RobotConfig, from_dict
    from arpz.robot.agent import RobotAgent
    from arpz.transport.memory import MemoryBus, MemoryTransport

    raw = {
        "robot_id": "r001",
        "connect": ["tcp/127.0.0.1:1"],
        "sensors": [{"name": "imu", "kind": "imu", "rate_hz": 10}],
        "reliability": "none",  # no CEDDP here: nothing to wait for at shutdown
        "clock": {"enabled": False},
        "match_timeout_s": 0.1,
    }
    config = from_dict(raw, RobotConfig, source="test")
    agent = RobotAgent(config, MemoryTransport(MemoryBus()))
    agent.start()
    try:
        deadline = time.monotonic() + 0.3
        while time.monotonic() < deadline:  # one core busy for 0.3 s
            pass
        busy = agent.stats(final=False).cpu_percent
        assert 10.0 <= busy <= 250.0, busy  # a core busy most of the interval, on a loaded host
        # asked again at once: the shared reading is not renewed, the figure is kept
        assert agent.stats(final=False).cpu_percent == busy
    finally:
        agent.shutdown()
