import itertools
import json
from pathlib import Path

import numpy as np
import pytest

from arpz.core.config import SensorConfig
from arpz.robot.sensors import make_driver, preset_sensors
from arpz.robot.sensors.base import SensorDriver, check_value
from arpz.robot.sensors.factory import DriverError
from arpz.robot.sensors.replay import TraceError
from arpz.robot.sensors.simulated import SIMULATED, _Quantiser

EXPECTED_TYPES = {
    "lidar": float,
    "dht11": float,
    "imu": float,
    "ultrasonic": float,
    "flame": bool,
    "pir": str,
    "light": str,
}


def readings(kind: str, seed: int, rate_hz: float = 50, seconds: float = 120) -> list[object]:
    driver = SIMULATED[kind]({}, seed)
    return [driver.read(i / rate_hz) for i in range(int(seconds * rate_hz))]


@pytest.mark.parametrize("kind", sorted(EXPECTED_TYPES))
def test_every_kind_gives_the_table_1_type_and_is_seeded(kind: str) -> None:
    values = readings(kind, seed=3)
    assert all(type(v) is EXPECTED_TYPES[kind] for v in values)
    assert values == readings(kind, seed=3)
    if kind in ("pir", "light"):
        assert set(values) <= {"detect", "not detect", "light", "dark"}


def run_lengths(values: list[object]) -> list[int]:
    runs, current = [], 1
    for a, b in itertools.pairwise(values):
        if a == b:
            current += 1
        else:
            runs.append(current)
            current = 1
    return [*runs, current]


def test_mostly_constant_sensors_repeat_and_imu_changes_most_of_the_time() -> None:
    # at 50 Hz over two minutes: a PIR / flame / light sensor holds its value for seconds,
    # a LIDAR beam for a good fraction of a second, an IMU rarely twice in a row
    for kind in ("pir", "flame", "light", "dht11"):
        assert max(run_lengths(readings(kind, seed=1))) >= 100, kind
    lidar = readings("lidar", seed=1)
    assert 2 < sum(run_lengths(lidar)) / len(run_lengths(lidar)) < 500
    assert len(set(lidar)) > 5  # people walk through the beam
    imu = readings("imu", seed=1)
    assert sum(run_lengths(imu)) / len(run_lengths(imu)) < 3


def test_presets_follow_seed_001() -> None:
    assert [s.kind for s in preset_sensors("machine1")] == [
        "lidar",
        "light",
        "flame",
        "dht11",
        "imu",
        "pir",
    ]
    assert [s.kind for s in preset_sensors("machine2")] == [
        "flame",
        "pir",
        "ultrasonic",
        "dht11",
        "light",
    ]
    with pytest.raises(ValueError, match="unknown preset"):
        preset_sensors("machine9")


def test_replay_csv_and_jsonl(tmp_path: Path) -> None:
    (tmp_path / "t.csv").write_text("t_s,value\n0,1.5\n1,2.5\n2,2.5\n")
    (tmp_path / "p.jsonl").write_text(
        "\n".join(
            json.dumps({"t_s": t, "value": v}) for t, v in [(0, "detect"), (0.5, "not detect")]
        )
    )
    csv_driver = make_driver(
        SensorConfig(name="a", kind="lidar", driver="replay", trace="t.csv"),
        robot_id="r",
        robot_seed=0,
        base_dir=tmp_path,
    )
    assert [csv_driver.read(t) for t in (0, 0.9, 1.0, 5.0)] == [1.5, 1.5, 2.5, 2.5]
    jsonl = make_driver(
        SensorConfig(
            name="p", kind="pir", driver="replay", trace="p.jsonl", options={"loop": True}
        ),
        robot_id="r",
        robot_seed=0,
        base_dir=tmp_path,
    )
    # a lap lasts from the first to the last record: at 0.5 s the last value, then round again
    assert [jsonl.read(t) for t in (0.1, 0.5, 0.6)] == ["detect", "not detect", "detect"]


@pytest.mark.parametrize(
    ("name", "text", "message"),
    [
        ("a.csv", "time,value\n0,1\n", "header"),
        ("b.csv", "t_s,value\n0,abc\n", "b.csv:2"),
        ("c.csv", "t_s,value\n1,1\n0,2\n", "must not decrease"),
        ("d.jsonl", '{"t": 0}\n', "d.jsonl:1"),
        ("e.csv", "t_s,value\n", "no records"),
    ],
)
def test_bad_traces_say_where(tmp_path: Path, name: str, text: str, message: str) -> None:
    (tmp_path / name).write_text(text)
    with pytest.raises(TraceError, match=message):
        make_driver(
            SensorConfig(name="a", kind="lidar", driver="replay", trace=name),
            robot_id="r",
            robot_seed=0,
            base_dir=tmp_path,
        )


class ConstantPir(SensorDriver):
    kind = "pir"

    def read(self, now_s: float) -> str:
        return "detect"


def test_user_driver_by_import_path_and_errors() -> None:
    config = SensorConfig(name="p", kind="pir", driver=f"{__name__}:ConstantPir")
    driver = make_driver(config, robot_id="r", robot_seed=0, base_dir=Path())
    assert driver.read(0) == "detect"
    with pytest.raises(DriverError, match="reads 'pir'"):
        make_driver(
            SensorConfig(name="p", kind="light", driver=f"{__name__}:ConstantPir"),
            robot_id="r",
            robot_seed=0,
            base_dir=Path(),
        )
    with pytest.raises(DriverError, match=r"cannot import module 'nowhere\.mod'"):
        make_driver(
            SensorConfig(name="p", kind="pir", driver="nowhere.mod:X"),
            robot_id="r",
            robot_seed=0,
            base_dir=Path(),
        )


def test_check_value_enforces_table_1() -> None:
    assert check_value("lidar", 3) == 3.0
    assert type(check_value("lidar", 3)) is float
    assert check_value("lidar", 2.5) == 2.5
    assert check_value("pir", "detect") == "detect"
    assert check_value("light", "dark") == "dark"
    assert check_value("flame", False) is False
    assert check_value("camera", b"\x00\x01") == b"\x00\x01"
    with pytest.raises(TypeError):
        check_value("flame", 1)
    with pytest.raises(TypeError, match="detect"):
        check_value("pir", "maybe")
    with pytest.raises(TypeError):
        check_value("lidar", True)  # a bool is an int, not a reading
    with pytest.raises(TypeError):
        check_value("camera", bytearray(2))
    with pytest.raises(TypeError):
        check_value("light", 1.0)


def test_a_quantised_reading_is_the_level_rounded_to_6_decimals_each_time() -> None:
    """The quantiser keeps each level's float: the same as computing it again, every time."""
    rng = np.random.default_rng(5)
    for step in (0.01, 0.3, 9.80665 / 16384):
        quantise = _Quantiser(step)
        for value in rng.normal(5.0, 3.0, 2000):
            expected = round(round(float(value) / step) * step, 6)
            assert quantise(float(value)) == expected
            assert quantise(float(value)) == expected  # the kept level


@pytest.mark.parametrize(("kind", "size"), [("camera", 640 * 480 * 3), ("pointcloud", 87_381 * 12)])
def test_large_kinds_give_seeded_bytes_of_their_size_that_change(kind: str, size: int) -> None:
    values = readings(kind, seed=3, rate_hz=10, seconds=2)
    assert all(type(v) is bytes and len(v) == size for v in values)
    assert values == readings(kind, seed=3, rate_hz=10, seconds=2)
    assert len(set(values)) == len(values)  # every frame differs, as a real camera's do
    assert check_value(kind, values[0]) is values[0]
    with pytest.raises(TypeError, match="must return bytes"):
        check_value(kind, "not a frame")


def test_a_dark_static_camera_repeats_and_a_smaller_one_is_smaller() -> None:
    dark = SIMULATED["camera"]({"noise": False, "idle_mean_s": 1e9}, 1)
    assert dark.read(0.1) == dark.read(0.2)
    assert len(SIMULATED["camera"]({"width": 320, "height": 240}, 1).read(0.0)) == 320 * 240 * 3


@pytest.mark.parametrize("height", [1, 4, 7, 8, 9])
def test_a_camera_fewer_than_8_rows_high_still_makes_frames(height: int) -> None:
    """Its band of fresh noise is 8 rows, or the whole frame when smaller (a crash before)."""
    camera = SIMULATED["camera"]({"width": 5, "height": height}, 1)
    first, second = camera.read(1.0), camera.read(2.5)
    assert len(first) == len(second) == 5 * height * 3 and first != second


def test_large_kinds_cannot_replay_text_traces() -> None:
    with pytest.raises(ValueError, match="cannot replay a trace"):
        SensorConfig(name="front", kind="camera", driver="replay", trace="t.csv")


@pytest.mark.parametrize("options", [{"width": -3}, {"height": "tall"}, {"width": True}])
def test_a_bad_camera_option_is_a_driver_error_naming_sensor_and_option(
    options: dict[str, object], tmp_path: Path
) -> None:
    sensor = SensorConfig(name="front", kind="camera", options=options)
    with pytest.raises(DriverError, match=r"sensor 'front' \(camera\): option (width|height)"):
        make_driver(sensor, robot_id="r1", robot_seed=0, base_dir=tmp_path)
