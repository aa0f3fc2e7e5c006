"""The camera and point-cloud replay drivers give back the frames a recording holds."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from arpz.core.config import SensorConfig
from arpz.core.rosmsg.convert import to_cdr
from arpz.robot.sensors import make_driver
from arpz.robot.sensors.replay import TraceError
from arpz.robot.sensors.simulated import SimCamera, SimPointCloud
from arpz.tools._recording import McapSink, Topic
from arpz.tools.frame_replay import CameraReplay, PointCloudReplay

CAMERA = {"width": 16, "height": 12}
BASE_NS = 1_700_000_000_000_000_000
TIMES_S = [0.0, 0.1, 0.2, 0.3]


def recording(path: Path, topics: tuple[str, ...] = ("cam",)) -> dict[str, list[bytes]]:
    """Frames of a SimCamera per topic, and a point cloud, written as ``arpz record`` does."""
    frames: dict[str, list[bytes]] = {}
    with McapSink(path, split_bytes=0, split_s=0.0, metadata={"fleet": "t"}) as sink:
        cloud = SimPointCloud({"points": 5}, seed=1)
        for name in topics:
            camera = SimCamera(CAMERA, seed=len(name))
            topic = Topic(f"arpz/t/robot/r/frames/{name}", "r", "camera", None)
            for t in TIMES_S:
                frame = camera.read(t)
                frames.setdefault(name, []).append(frame)
                stamp = BASE_NS + int(t * 1e9)
                data = to_cdr("camera", frame, stamp_ns=stamp, frame_id=f"r/{name}", size=(16, 12))
                sink.write(topic, data, log_ns=stamp, publish_ns=stamp, sequence=0)
        topic = Topic("arpz/t/robot/r/frames/scan", "r", "pointcloud", None)
        value = cloud.read(0.0)
        frames["scan"] = [value]
        data = to_cdr("pointcloud", value, stamp_ns=BASE_NS, frame_id="r/scan")
        sink.write(topic, data, log_ns=BASE_NS, publish_ns=BASE_NS, sequence=0)
    return frames


def test_the_replayed_frames_are_the_recorded_ones_at_their_times(tmp_path: Path) -> None:
    frames = recording(tmp_path / "r.mcap")
    driver = CameraReplay({"recording": str(tmp_path / "r.mcap")}, seed=0)
    assert [driver.read(t + 0.05) for t in TIMES_S] == frames["cam"]
    assert driver.read(10.0) == frames["cam"][-1]  # holds the last frame
    looping = CameraReplay({"recording": str(tmp_path / "r.mcap"), "loop": True}, seed=0)
    assert looping.read(0.4 + 0.15) == frames["cam"][1]  # the loop lasts 4 frames of 0.1 s
    cloud = PointCloudReplay({"recording": str(tmp_path / "r.mcap")}, seed=0)
    assert cloud.read(0.0) == frames["scan"][0]


def test_a_robot_loads_it_by_its_path(tmp_path: Path) -> None:
    frames = recording(tmp_path / "r.mcap")
    sensor = SensorConfig(
        name="front",
        kind="camera",
        driver="arpz.tools.frame_replay:CameraReplay",
        options={"recording": str(tmp_path / "r.mcap"), "topic": "/r/cam"},
    )
    driver = make_driver(sensor, robot_id="r", robot_seed=0, base_dir=tmp_path)
    assert driver.read(0.0) == frames["cam"][0]


def test_errors_name_the_file_and_what_to_do(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    recording(tmp_path / "two.mcap", topics=("left", "right"))
    with pytest.raises(TraceError, match=r"2 camera topics .* name one in the driver's 'topic'"):
        CameraReplay({"recording": str(tmp_path / "two.mcap")}, seed=0)
    with pytest.raises(TraceError, match=r"no topic '/r/none' of kind camera"):
        CameraReplay({"recording": str(tmp_path / "two.mcap"), "topic": "/r/none"}, seed=0)
    with pytest.raises(TraceError, match=r"needs options\.recording"):
        CameraReplay({}, seed=0)
    (tmp_path / "bad.mcap").write_bytes(b"garbage")
    with pytest.raises(TraceError, match=r"bad\.mcap: not a readable"):
        CameraReplay({"recording": str(tmp_path / "bad.mcap")}, seed=0)
    monkeypatch.setitem(sys.modules, "mcap.reader", None)  # a robot install: no mcap
    with pytest.raises(TraceError, match=r"needs the mcap and rosbags libraries .*arpz\[server\]"):
        CameraReplay({"recording": str(tmp_path / "two.mcap")}, seed=0)
