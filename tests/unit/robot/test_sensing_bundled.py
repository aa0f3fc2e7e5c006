"""A robot's bundled sensor writers do not batch: a topic sensed twice within
``batch_max_delay_s`` (a late robot's catch-up tick) still leaves in its own tick's bundle
instead of waiting in the writer's batch for the writer's thread."""

from __future__ import annotations

from pathlib import Path

from arpz.channel.bundling import Bundler
from arpz.core.config import RobotConfig, from_dict
from arpz.robot.sensing import build_sensors, sense
from arpz.transport.memory import MemoryBus, MemoryTransport


def _config(*, bundles: bool) -> RobotConfig:
    raw = {
        "robot_id": "r1",
        "fleet": "f",
        "connect": ["tcp/127.0.0.1:7447"],
        "sensors": [{"name": "imu", "kind": "imu", "rate_hz": 100.0}],
        "local_cache": {"enabled": False},
        "bundle_sensors": bundles,
    }
    return from_dict(raw, RobotConfig, source="test")


def test_a_catch_up_tick_leaves_in_its_bundle_not_in_a_writer_batch(tmp_path: Path) -> None:
    bus = MemoryBus()
    raw: list[str] = []  # what crosses the bus, at the instant it does
    bus.subscribers.append(("**", lambda key, _p, _a: raw.append(key)))
    config = _config(bundles=True)
    bundler = Bundler(MemoryTransport(bus), max_bytes=1280)
    (imu,) = build_sensors(config, bundler, None, tmp_path)
    try:
        assert imu.output.writer.qos.batch_max_samples == 1
        for now_s in (1.0, 1.0001):  # the same topic twice within 0.5 ms
            with bundler.collect():
                sense(imu, now_s, "r1")
        sensor_key = "arpz/f/robot/r1/sensor/imu"
        # each tick's sample left as the tick ended (alone in its tick: on its own key)
        assert raw.count(sensor_key) == 2, raw
        assert bundler.stats.single == 2
    finally:
        imu.close()


def test_an_unbundled_robot_keeps_the_profile_s_batching(tmp_path: Path) -> None:
    config = _config(bundles=False)
    (imu,) = build_sensors(config, MemoryTransport(MemoryBus()), None, tmp_path)
    try:
        assert imu.output.writer.qos.batch_max_samples == config.sensor_qos.batch_max_samples > 1
    finally:
        imu.close()
