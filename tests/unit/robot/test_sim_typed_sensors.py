"""The simulated typed sensors (issue 41): ``driver = "sim"`` with ``type =
"sensor_msgs/msg/LaserScan"``, ``Image`` or ``CompressedImage`` gives whole messages that the
robot's boundary check takes: a LIDAR's scan of a room (angles consistent, ``range_max``
finite, seeded), raw RGB frames and JPEG frames that decode to their size; and the config
allows ``sim`` for exactly those types, naming them otherwise."""

from __future__ import annotations

import io
import itertools
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from arpz.core.config import SIMULATED_TYPES, ConfigError, RobotConfig, SensorConfig, from_dict
from arpz.core.msgtypes import MessageTypes, MessageValueError
from arpz.robot.sensors import make_driver
from arpz.robot.sensors.factory import DriverError
from arpz.robot.sensors.simulated import SIMULATED_MESSAGES, SimLaserScan

SCAN = "sensor_msgs/msg/LaserScan"
IMAGE = "sensor_msgs/msg/Image"
JPEG = "sensor_msgs/msg/CompressedImage"
TYPES = MessageTypes()


def driver(
    msg_type: str, options: dict[str, Any] | None = None, *, seed: int = 3, rate_hz: float = 10
) -> Any:
    sensor = SensorConfig(
        name="s", type=msg_type, rate_hz=rate_hz, seed=seed, options=options or {}
    )
    return make_driver(sensor, robot_id="r1", robot_seed=0, base_dir=Path("."))


def checked(msg_type: str, raw: object, nan: Any = "refuse") -> Any:
    return TYPES.check(msg_type, raw, nan=nan, stamp_ns=1_700_000_000_123_456_789, frame_id="s")


def scans(options: dict[str, Any] | None = None, seed: int = 3, n: int = 20) -> list[Any]:
    lidar = driver(SCAN, options, seed=seed)
    return [checked(SCAN, lidar.read(i / 10)) for i in range(n)]


# -- LaserScan ----------------------------------------------------------------------------------


def test_a_scan_has_its_beams_over_a_full_turn_with_consistent_angles() -> None:
    scan = scans(n=1)[0]
    assert len(scan.ranges) == 360 and scan.intensities == []
    assert scan.angle_min == pytest.approx(-math.pi)
    assert scan.angle_increment == pytest.approx(2 * math.pi / 360)
    assert scan.angle_max == pytest.approx(scan.angle_min + 359 * scan.angle_increment)
    # what every LaserScan reader computes: one range per angle from min to max
    span = (scan.angle_max - scan.angle_min) / scan.angle_increment
    assert round(span) + 1 == len(scan.ranges)
    assert (scan.range_min, scan.range_max) == pytest.approx((0.12, 12.0))
    assert math.isfinite(scan.range_max)
    assert scan.scan_time == pytest.approx(0.1)
    assert scan.time_increment * 360 == pytest.approx(scan.scan_time)
    assert scan.header.frame_id == "s" and scan.header.stamp.nanosec == 123_456_789
    # a room of at most 8 x 6 m with the robot inside: every beam returns, within its diagonal
    assert all(scan.range_min <= r <= 10.0 for r in scan.ranges)


def test_a_partial_field_of_view_has_its_first_and_last_beams_on_its_edges() -> None:
    lidar = driver(SCAN, {"beams": 1081, "fov_deg": 270, "intensities": True}, rate_hz=40)
    scan = checked(SCAN, lidar.read(0.0))
    assert len(scan.ranges) == len(scan.intensities) == 1081
    assert scan.angle_min == pytest.approx(-math.radians(135))
    assert scan.angle_max == pytest.approx(math.radians(135))
    assert scan.angle_increment == pytest.approx(math.radians(0.25))
    assert round((scan.angle_max - scan.angle_min) / scan.angle_increment) + 1 == 1081
    assert scan.scan_time == pytest.approx(1 / 40)
    assert scan.time_increment == pytest.approx(scan.scan_time * math.radians(0.25) / (2 * math.pi))
    assert all(10.0 <= i <= 100.0 for i in scan.intensities)


def test_every_beam_ends_on_a_wall_of_the_room() -> None:
    lidar = SimLaserScan({"room_m": [5.0, 4.0], "noise_m": 0.0, "idle_mean_s": 1e9}, seed=7)
    ranges = lidar.read(1.0)["ranges"]
    ends = lidar.origin + lidar.rays * ranges[:, None]
    on_wall = (
        np.isclose(ends[:, 0], 0.0, atol=2e-3)
        | np.isclose(ends[:, 0], 5.0, atol=2e-3)
        | np.isclose(ends[:, 1], 0.0, atol=2e-3)
        | np.isclose(ends[:, 1], 4.0, atol=2e-3)
    )
    assert on_wall.all()
    assert ranges.min() >= 0.5 - 1e-3  # the robot stands at least 0.5 m from every wall


def test_scans_are_seeded_noisy_and_a_person_walks_through_now_and_then() -> None:
    first = scans(seed=3, n=50)
    assert [s.ranges for s in first] == [s.ranges for s in scans(seed=3, n=50)]
    assert first[0].ranges != scans(seed=4, n=1)[0].ranges
    assert all(a.ranges != b.ranges for a, b in itertools.pairwise(first))
    quiet = scans({"noise_m": 0.0, "idle_mean_s": 1e9}, n=3)
    assert quiet[0].ranges == quiet[1].ranges == quiet[2].ranges  # the local cache holds back
    lidar = SimLaserScan({"noise_m": 0.0, "idle_mean_s": 0.5, "room_m": [6.0, 5.0]}, seed=1)
    empty = lidar.walls
    nearer = [int((lidar.read(t / 10)["ranges"] < empty - 0.05).sum()) for t in range(300)]
    assert max(nearer) > 0, "a person crossing the room shortens some beams"


def test_beyond_range_max_reads_inf_which_refuse_all_refuses() -> None:
    lidar = driver(SCAN, {"range_max": 2.0, "room_m": [8.0, 8.0]})
    scan = checked(SCAN, lidar.read(0.0))
    assert math.inf in scan.ranges and scan.range_max == 2.0  # REP 117: no return is +inf
    assert all(r <= 2.0 for r in scan.ranges if math.isfinite(r))
    with pytest.raises(MessageValueError, match="ranges holds a NaN or infinity"):
        checked(SCAN, lidar.read(0.1), nan="refuse_all")


# -- Image and CompressedImage ------------------------------------------------------------------


def test_an_image_is_rgb8_of_its_size_seeded_and_every_frame_differs() -> None:
    camera = driver(IMAGE)
    frames = [checked(IMAGE, camera.read(i / 10)) for i in range(5)]
    image = frames[0]
    assert (image.width, image.height, image.encoding, image.step) == (640, 480, "rgb8", 1920)
    assert image.is_bigendian == 0 and len(image.data) == 640 * 480 * 3
    assert len({f.data for f in frames}) == 5
    again = driver(IMAGE)
    assert [checked(IMAGE, again.read(i / 10)).data for i in range(5)] == [f.data for f in frames]
    small = checked(IMAGE, driver(IMAGE, {"width": 320, "height": 240}).read(0.0))
    assert (small.width, small.height, small.step, len(small.data)) == (320, 240, 960, 230_400)
    still = driver(IMAGE, {"noise": False, "idle_mean_s": 1e9})
    assert still.read(0.1)["data"].tobytes() == still.read(0.2)["data"].tobytes()


def test_a_compressed_image_is_a_jpeg_of_its_size() -> None:
    simplejpeg = pytest.importorskip("simplejpeg")
    camera = driver(JPEG)
    message = checked(JPEG, camera.read(0.5))
    assert message.format == "jpeg" and message.data[:2] == b"\xff\xd8"
    pixels = simplejpeg.decode_jpeg(message.data)
    assert pixels.shape == (480, 640, 3)
    original = driver(IMAGE).read(0.5)["data"]  # the same seed: the same frame, raw
    assert np.abs(pixels.astype(int) - original.astype(int)).mean() < 8
    assert 10_000 < len(message.data) < 100_000  # a scene, not noise: JPEG compresses it
    assert checked(JPEG, driver(JPEG).read(0.5)).data == message.data  # seeded
    small = checked(JPEG, driver(JPEG, {"width": 321, "height": 243, "quality": 30}).read(0.0))
    from PIL import Image

    with Image.open(io.BytesIO(small.data)) as decoded:
        assert (decoded.format, decoded.size) == ("JPEG", (321, 243))
    low = checked(JPEG, driver(JPEG, {"quality": 30}).read(0.5))
    assert len(low.data) < len(message.data)


def test_a_compressed_image_without_simplejpeg_says_what_to_install(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setitem(sys.modules, "simplejpeg", None)  # an import of it raises ImportError
    with pytest.raises(DriverError, match=r"simplejpeg.*pip install 'arpz\[jpeg\]'") as error:
        driver(JPEG)
    assert "sensor 's' (sensor_msgs/msg/CompressedImage)" in str(error.value)


# -- options and the config rule ----------------------------------------------------------------


@pytest.mark.parametrize(
    ("msg_type", "options", "says"),
    [
        (SCAN, {"beams": 0}, "option beams must be an integer >= 1"),
        (SCAN, {"fov_deg": 400}, "option fov_deg must be a finite number from"),
        (SCAN, {"fov_deg": 180, "beams": 1}, "beams must be >= 2"),
        (SCAN, {"range_max": math.inf}, "option range_max must be a finite number"),
        (SCAN, {"range_min": 2.0, "range_max": 2.0}, "range_max .2. must be above range_min"),
        (SCAN, {"room_m": [3.0]}, "option room_m must be .width, depth."),
        (SCAN, {"room_m": [0.5, 3.0]}, "option room_m must be a finite number >= 1"),
        (SCAN, {"beam": 180}, "unknown option beam: a simulated sensor_msgs/msg/LaserScan takes"),
        (IMAGE, {"width": 0}, "option width must be an integer >= 1"),
        (IMAGE, {"quality": 50}, "unknown option quality"),
        (JPEG, {"quality": 0}, "option quality must be an integer from 1 to 100"),
        (JPEG, {"quality": 80.5}, "option quality must be an integer from 1 to 100"),
    ],
)
def test_a_bad_option_is_a_driver_error_naming_sensor_and_option(
    msg_type: str, options: dict[str, Any], says: str
) -> None:
    with pytest.raises(DriverError, match=rf"sensor 's' \({msg_type}\): .*{says}"):
        driver(msg_type, options)


def test_the_config_and_the_drivers_name_the_same_simulated_types() -> None:
    assert set(SIMULATED_MESSAGES) == set(SIMULATED_TYPES)
    for msg_type in SIMULATED_TYPES:
        assert SensorConfig(name="s", type=msg_type).driver == "sim"
        assert TYPES.known(msg_type)


def test_sim_for_a_type_without_a_simulated_driver_is_refused_naming_those_with_one() -> None:
    with pytest.raises(ConfigError) as error:
        from_dict(
            {"robot_id": "r1", "sensors": [{"name": "gps", "type": "sensor_msgs/msg/NavSatFix"}]},
            RobotConfig,
            source="robot.toml",
        )
    text = str(error.value)
    assert "sensor 'gps' of type sensor_msgs/msg/NavSatFix: no simulated driver" in text
    assert all(msg_type in text for msg_type in SIMULATED_TYPES)
    assert "driver = 'module.path:ClassName'" in text
    with pytest.raises(ValueError, match="a typed sensor cannot replay a trace"):
        SensorConfig(name="scan", type=SCAN, driver="replay", trace="scan.csv")
    # a driver class is still the way for any type, the simulated ones too
    assert SensorConfig(name="scan", type=SCAN, driver="mylab.lidar:Rplidar").type == SCAN
