"""A typed sensor on the robot (issue 41): the driver's message is checked against the topic's
ROS 2 type at the boundary (a message that does not fit is a driver error, never a sample), the
header is stamped when left out, an unchanged message is held back by the local cache (header
stamp excluded, within its deadbands), and what goes out is a ``MessageSample`` the CEDDP
decodes back to the same message."""

from __future__ import annotations

import math
from typing import Any

from arpz.core.config import SensorConfig
from arpz.core.messages import MESSAGE_SAMPLE_DECODER
from arpz.core.msgtypes import MessageTypes, same_message
from arpz.robot.local_cache import LocalCache
from arpz.robot.sensing import SensorChannel, sense
from tests.unit.robot.test_sensor_health import _outlet, _Script

NAVSAT = "sensor_msgs/msg/NavSatFix"
TYPES = MessageTypes()


def fix(latitude: float = 51.4545, **changes: Any) -> dict[str, Any]:
    return {
        "status": {"status": 0, "service": 1},
        "latitude": latitude,
        "longitude": -2.5879,
        "altitude": 11.0,
        "position_covariance": [0.0] * 9,
        "position_covariance_type": 0,
        **changes,
    }


def gps(values: list[Any], *, deadband: dict[str, float] | None = None) -> SensorChannel:
    config = SensorConfig(
        name="gps",
        type=NAVSAT,
        driver="mylab.drivers:Gps",
        rate_hz=10,
        cache_deadband=deadband or {},
    )
    return SensorChannel(
        config=config,
        driver=_Script(values),  # type: ignore[arg-type]
        cache=LocalCache(
            max_silence_s=60.0,
            same=lambda a, b: same_message(a, b, config.cache_deadband),
        ),
        output=_outlet(),  # type: ignore[arg-type]
        rate_hz=10,
        types=TYPES,
    )


def sent_messages(sensor: SensorChannel) -> list[Any]:
    samples = [MESSAGE_SAMPLE_DECODER.decode(p) for p in sensor.output.sent]  # type: ignore[union-attr]
    return [TYPES.decode(NAVSAT, s.value) for s in samples]


def test_a_typed_reading_goes_out_stamped_and_comes_back_the_same() -> None:
    sensor = gps([fix()])
    sensor.wall_ns = lambda: 1_733_400_000_250_000_000
    sense(sensor, 0.0, "r1:abc")
    (message,) = sent_messages(sensor)
    assert message.latitude == 51.4545
    assert (message.header.stamp.sec, message.header.stamp.nanosec) == (1_733_400_000, 250_000_000)
    assert message.header.frame_id == "gps"


def test_a_message_that_does_not_fit_its_type_is_a_driver_error() -> None:
    values = [fix(latitude="north"), fix(bogus=1), {"latitude": 1.0}, fix(altitude=math.nan), fix()]
    sensor = gps(values)
    for i in range(len(values)):
        sense(sensor, i * 0.1, "r1:abc")
    c = sensor.counters()
    assert (c.values_refused, c.sent) == (4, 1)
    assert c.produced == c.sent + c.held_back + c.write_failures + c.driver_errors
    assert "NavSatFix.altitude is nan" in c.last_driver_error


def test_an_unchanged_message_is_held_back_whatever_its_stamp_and_within_its_deadband() -> None:
    values = [fix(), fix(), fix(latitude=51.4545 + 5e-7), fix(latitude=51.46)]
    sensor = gps(values, deadband={"latitude": 1e-6})
    clock = iter(range(1, 10))
    sensor.wall_ns = lambda: next(clock) * 1_000_000_000  # a new stamp every read
    for i in range(len(values)):
        sense(sensor, i * 0.1, "r1:abc")
    c = sensor.counters()
    assert (c.sent, c.held_back) == (2, 2)
    assert [m.latitude for m in sent_messages(sensor)] == [51.4545, 51.46]
