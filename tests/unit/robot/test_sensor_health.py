"""A failing sensor is never silent (issue 41): every read is produced, a read that gives no
reading is a driver error (an exception, or a value refused: the wrong type, NaN or infinity),
counted per sensor and logged once per cause every interval for as long as it lasts; a read
longer than its period is counted late; a sensor with no reading for a whole interval is named
in the robot's stats."""

from __future__ import annotations

import logging
import math
import threading
from typing import Any

import pytest

from arpz.core import keys
from arpz.core.config import RobotClockConfig, RobotConfig, SensorConfig
from arpz.core.messages import STATS_DECODER, RobotStats, encode
from arpz.core.throttled_log import ThrottledLog
from arpz.robot import sensing
from arpz.robot.agent import DuplicateRobotError, RobotAgent, check_robot_id_free
from arpz.robot.local_cache import LocalCache
from arpz.robot.sensing import SensorChannel, sense
from arpz.robot.sensors.base import SensorDriver
from arpz.transport.memory import MemoryBus, MemoryTransport
from tests.unit.robot.test_frame_sender import _SlowLink


def _outlet() -> _SlowLink:
    """The channel writer's stand-in (a link that never waits): keeps what was sent."""
    link = _SlowLink()
    link.gate.set()
    return link


class _Script:
    """A driver that plays ``values``: an exception instance is raised, anything else returned."""

    def __init__(self, values: list[Any]) -> None:
        self.values = list(values)

    def read(self, _now_s: float) -> Any:
        value = self.values.pop(0)
        if isinstance(value, BaseException):
            raise value
        return value

    def close(self) -> None:
        pass


def _channel(values: list[Any], *, nan: str = "refuse", rate_hz: float = 10.0) -> SensorChannel:
    config = SensorConfig(name="temp", kind="dht11", rate_hz=rate_hz, nan=nan)  # type: ignore[arg-type]
    return SensorChannel(
        config=config,
        driver=_Script(values),  # type: ignore[arg-type]
        cache=LocalCache(enabled=True, tolerance=0.0, max_silence_s=60.0),
        output=_outlet(),  # type: ignore[arg-type]
        rate_hz=rate_hz,
    )


def test_every_read_is_produced_and_the_ones_without_a_reading_are_driver_errors() -> None:
    values = [20.0, OSError("i2c bus stuck"), 20.0, math.nan, 21.0, "warm", math.inf, 21.0]
    sensor = _channel(values)
    for i in range(len(values)):
        sense(sensor, now_s=i * 0.1, writer="r1:abc")
    c = sensor.counters()
    assert c.produced == len(values) == c.sent + c.held_back + c.write_failures + c.driver_errors
    assert (c.sent, c.held_back) == (2, 2)  # 20.0, 21.0 sent; their repeats held back
    assert (c.driver_errors, c.driver_exceptions, c.values_refused) == (4, 1, 3)
    assert c.last_driver_error.startswith("value refused: a dht11 driver returned inf")
    assert all(b"nan" not in p and b"inf" not in p for p in sensor.output.sent)  # type: ignore[union-attr]


def test_refuse_all_refuses_a_scalar_nan_too() -> None:
    sensor = _channel([math.nan, 1.0], nan="refuse_all")
    sense(sensor, 0.0, "r1:abc")
    sense(sensor, 0.1, "r1:abc")
    assert (sensor.counters().sent, sensor.counters().values_refused) == (1, 1)


def test_nan_pass_sends_nan_and_infinity_as_readings() -> None:
    sensor = _channel([math.nan, -math.inf], nan="pass")
    sense(sensor, 0.0, "r1:abc")
    sense(sensor, 0.1, "r1:abc")
    c = sensor.counters()
    assert (c.sent, c.driver_errors) == (2, 0)


def test_the_nan_option_is_checked_when_the_config_is_loaded() -> None:
    from arpz.core.config import ConfigError, from_dict

    sensor = {"name": "t", "kind": "dht11", "nan": "ignore"}
    with pytest.raises(ConfigError, match="nan"):
        from_dict({"robot_id": "r1", "sensors": [sensor]}, RobotConfig, source="robot.toml")


def test_the_log_keeps_one_line_per_cause_per_interval_for_as_long_as_it_lasts(
    caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Not only the first hundred errors: 25 000 reads over 250 s of a driver that always
    raises give one line at the start and one every 10 s after, each with its count."""
    clock = [0.0]
    throttled = ThrottledLog(logging.getLogger(sensing.__name__), clock=lambda: clock[0])
    monkeypatch.setattr(sensing, "throttled", throttled)
    reads = 25_000
    sensor = _channel([OSError("no device")] * reads + [ValueError("bad")] * 3, rate_hz=100.0)
    with caplog.at_level(logging.ERROR, logger="arpz.robot.sensing"):
        for i in range(reads):
            clock[0] = i / 100
            sense(sensor, clock[0], "r1:abc")
        for _ in range(3):  # a second cause gets its own line at once
            sense(sensor, clock[0], "r1:abc")
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 26, lines[-3:]  # one per 10 s over 250 s, and the other cause's
    assert lines[0] == "sensor temp: driver error #1: OSError: no device"
    assert "and 999 more like it in the last 10 s" in lines[-2], lines[-2]
    assert "ValueError: bad" in lines[-1]
    assert sensor.counters().driver_exceptions == reads + 3


def test_a_read_longer_than_the_period_is_late_and_still_sent(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    ticks = iter([0.0, 0.25, 1.0, 1.01])  # perf_counter around each read: 0.25 s, then 0.01 s
    monkeypatch.setattr(sensing, "perf_counter", lambda: next(ticks))
    sensor = _channel([20.0, 21.0], rate_hz=10.0)
    sense(sensor, 0.0, "r1:abc")
    sense(sensor, 0.1, "r1:abc")
    c = sensor.counters()
    assert (c.late_reads, c.sent, c.driver_errors) == (1, 2, 0)


def test_a_sensor_without_a_reading_for_an_interval_is_silent() -> None:
    sensor = _channel([20.0] + [OSError("gone")] * 50, rate_hz=10.0)
    sense(sensor, 0.0, "r1:abc")
    assert not sensor.silent(now_s=0.4, interval_s=0.5)
    for i in range(1, 11):
        sense(sensor, i * 0.1, "r1:abc")
    assert sensor.silent(now_s=1.0, interval_s=0.5)
    # a slow sensor is not silent between its reads: two of its periods must pass
    slow = _channel([20.0], rate_hz=0.2)
    sense(slow, 0.0, "r1:abc")
    assert not slow.silent(now_s=5.0, interval_s=0.5)
    assert slow.silent(now_s=10.0, interval_s=0.5)


class _Raises(SensorDriver):
    kind = "dht11"

    def read(self, _now_s: float) -> float:
        raise OSError("no DHT11 on pin 4")


def test_the_robot_reports_its_driver_errors_and_silent_sensors() -> None:
    config = RobotConfig(
        robot_id="r1",
        fleet="f",
        match_timeout_s=0.05,
        reliability="none",  # no CEDDP to acknowledge the final report
        clock=RobotClockConfig(enabled=False),  # nor to answer the clock's requests
        sensors=[
            SensorConfig(
                name="temp",
                kind="dht11",
                rate_hz=50.0,
                driver="tests.unit.robot.test_sensor_health:_Raises",
            ),
            SensorConfig(name="ok", kind="lidar", rate_hz=50.0),
        ],
    )
    bus = MemoryBus()
    agent = RobotAgent(config, MemoryTransport(bus))
    agent.start()
    stop = threading.Event()
    thread = threading.Thread(target=agent.run, args=(stop,))
    thread.start()
    try:
        stop.wait(0.3)
        stats = agent.stats(final=False)
    finally:
        stop.set()
        thread.join(5)
        agent.shutdown()
    temp, ok = stats.topics["temp"], stats.topics["ok"]
    assert temp.driver_errors == temp.driver_exceptions == temp.produced > 0
    assert temp.sent == 0 and temp.last_driver_error == "OSError: no DHT11 on pin 4"
    assert ok.driver_errors == 0 and ok.sent > 0
    assert stats.silent_sensors == ["temp"]
    assert stats.started_ns > 0
    decoded = STATS_DECODER.decode(encode(stats))  # and an older CEDDP's decoder ignores them
    assert decoded.topics["temp"].driver_errors == temp.driver_errors


def _stats(incarnation: str, *, final: bool = False) -> RobotStats:
    return RobotStats(
        robot="r1", incarnation=incarnation, stamp_ns=1, final=final, topics={}, started_ns=5
    )


def test_a_second_process_with_a_robot_id_in_use_is_refused() -> None:
    bus = MemoryBus()
    first = MemoryTransport(bus)
    first.declare_token(keys.presence_key("f", "r1"))
    config = RobotConfig(robot_id="r1", fleet="f")
    stop = threading.Event()

    def report() -> None:  # the first process reports as it runs
        while not stop.wait(0.05):
            first.put(keys.stats_key("f", "r1"), encode(_stats("aaaa")))

    reporter = threading.Thread(target=report)
    reporter.start()
    try:
        with pytest.raises(DuplicateRobotError, match="robot_id 'r1' is in use: another process"):
            check_robot_id_free(MemoryTransport(bus), config, linger_s=5.0, history_s=0.2)
    finally:
        stop.set()
        reporter.join(5)


def test_a_previous_run_whose_token_lingers_is_waited_for_then_free() -> None:
    bus = MemoryBus()
    previous = MemoryTransport(bus)
    token = previous.declare_token(keys.presence_key("f", "r1"))
    threading.Timer(0.3, token.undeclare).start()  # the router's lease of the crashed run ends
    config = RobotConfig(robot_id="r1", fleet="f")
    waited = check_robot_id_free(MemoryTransport(bus), config, linger_s=5.0, history_s=0.2)
    assert 0.2 <= waited < 2.0


def test_a_token_that_outlives_the_lease_without_reports_is_refused() -> None:
    bus = MemoryBus()
    MemoryTransport(bus).declare_token(keys.presence_key("f", "r1"))
    config = RobotConfig(robot_id="r1", fleet="f")
    with pytest.raises(DuplicateRobotError, match="stayed alive"):
        check_robot_id_free(MemoryTransport(bus), config, linger_s=0.3, history_s=0.1)


def test_a_free_robot_id_costs_the_history_wait_only() -> None:
    config = RobotConfig(robot_id="r1", fleet="f")
    waited = check_robot_id_free(MemoryTransport(MemoryBus()), config, linger_s=5, history_s=0.1)
    assert waited < 1.0
