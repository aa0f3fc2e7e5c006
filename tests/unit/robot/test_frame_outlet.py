"""A robot's camera and point-cloud outlets cut frames for the robot's link."""

from __future__ import annotations

import pytest

from arpz.channel.io import FrameOutlet
from arpz.core.config import RobotConfig, SensorConfig
from arpz.core.protocol.fragments import DEFAULT_FRAGMENT_BYTES, STREAM_FRAGMENT_BYTES
from arpz.robot.sensing import sensor_outlet
from arpz.transport.memory import MemoryBus, MemoryTransport


def test_a_robot_takes_its_links_fragment_size_unless_told() -> None:
    camera = SensorConfig(name="front", kind="camera", rate_hz=1.0)
    bus = MemoryBus()
    for connect, given, expected in (
        (["tcp/127.0.0.1:7447"], None, STREAM_FRAGMENT_BYTES),
        (["udp/127.0.0.1:7447"], None, DEFAULT_FRAGMENT_BYTES),
        (["tcp/127.0.0.1:7447"], 4096, 4096),
    ):
        config = RobotConfig(
            robot_id="r1", connect=connect, sensors=[camera], frame_fragment_bytes=given
        )
        outlet = sensor_outlet(config, camera, MemoryTransport(bus))
        assert isinstance(outlet, FrameOutlet)
        try:
            assert outlet.frames.fragment_bytes == expected
        finally:
            outlet.close()
    with pytest.raises(ValueError, match="frame_fragment_bytes"):
        RobotConfig(robot_id="r1", frame_fragment_bytes=70_000)
