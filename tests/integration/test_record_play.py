"""``arpz record`` and ``arpz play`` against real fleets through a real router.

1. A robot with every sensor kind (the seven of seed 001 Table 1, a camera and a point cloud) and
   the Hello probe is recorded while a CEDDP runs; the file is read back WHOLE with INDEPENDENT
   readers (mcap-ros2-support's ``read_ros2_messages`` and its CDR decoder, rosbags' rosbag2
   reader and its AnyReader), and its counts are checked against the robot's own final counters.
   A second recorder with ``--include-internal`` runs beside it: its file is read whole by the
   mcap library, the JSON channels by a JSON decoder.
2. The hallway mission is recorded, commands included, and played into a fresh CEDDP running
   the same planner: the commands it sends are the recorded ones.
"""

from __future__ import annotations

import bisect
import json
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from arpz.core.messages import RobotStats
from arpz.core.rosmsg.convert import deserialize
from arpz.core.rosmsg.reports import DIAGNOSTIC_ARRAY, message_from_cdr
from tests.integration.fleet import Process, ceddp, settle

pytestmark = pytest.mark.integration

SENSORS = {
    "lidar": "sensor_msgs/msg/LaserScan",
    "dht11": "sensor_msgs/msg/Temperature",
    "imu": "sensor_msgs/msg/Imu",
    "ultrasonic": "sensor_msgs/msg/Range",
    "flame": "std_msgs/msg/Bool",
    "pir": "std_msgs/msg/Bool",
    "light": "sensor_msgs/msg/Illuminance",
    "cam": "sensor_msgs/msg/Image",
    "cloud": "sensor_msgs/msg/PointCloud2",
}


def record(endpoint: str, out: Path, cwd: Path, *args: str) -> Process:
    proc = Process(
        "record",
        [
            "-m",
            "arpz.tools.record",
            *("--connect", endpoint, "--fleet", "itest", "--out", str(out)),
            *("--json", str(out.with_suffix(".json"))),
            *args,
        ],
        cwd,
    )
    proc.wait_for("recording fleet")
    return proc


def robot(cwd: Path, name: str, text: str) -> Process:
    config = cwd / f"{name}.toml"
    config.write_text(f'robot_id = "{name}"\nfleet = "itest"\nstats_period_s = 0.2\n{text}')
    proc = Process(name, ["-m", "arpz.robot", "--config", str(config)], cwd)
    proc.wait_for("running")
    return proc


def messages(path: Path) -> dict[str, list[tuple[Any, Any, Any]]]:
    """topic -> [(schema, channel, message)], read by the mcap library alone."""
    out: dict[str, list[tuple[Any, Any, Any]]] = {}
    with path.open("rb") as stream:
        for schema, channel, message in make_reader(stream).iter_messages(log_time_order=True):
            out.setdefault(channel.topic, []).append((schema, channel, message))
    return out


def read_ros2_whole(path: Path) -> list[Any]:
    """Every message of the file, decoded by mcap-ros2-support's high-level reader with no
    topic filter (it raises on the first channel it cannot decode). The module warns that it is
    deprecated in favour of the decoder factory (the other reads here): it is what a user of
    the library calls, so it is called."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        from mcap_ros2.reader import read_ros2_messages

        return list(read_ros2_messages(path))


def message_count(path: Path) -> int:
    with path.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None and summary.statistics is not None
    return int(summary.statistics.message_count)


@pytest.fixture(scope="module")
def every_kind(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A recording of one robot with every sensor kind and the Hello probe, from before it
    started to after its final report (so every sample it sent should be in the file); beside
    it, ``internal.mcap`` made with ``--include-internal``."""
    tmp = tmp_path_factory.mktemp("every_kind")
    out = tmp / "fleet.mcap"
    with ceddp(tmp) as (_, endpoint):
        recorder = record(endpoint, out, tmp, "--camera-size", "64x48")
        internal = record(endpoint, tmp / "internal.mcap", tmp, "--include-internal")
        kinds = {name: name for name in list(SENSORS)[:7]} | {
            "cam": "camera",
            "cloud": "pointcloud",
        }
        options = {"cam": "{ width = 64, height = 48 }", "cloud": "{ points = 100 }"}
        sensors = "".join(
            f'[[sensors]]\nname = "{name}"\nkind = "{kind}"\nrate_hz = 20.0\n'
            f"options = {options.get(name, '{}')}\n"
            for name, kind in kinds.items()
        )
        # no local cache: every reading goes out, so every topic has many samples to count
        text = (
            f'connect = ["{endpoint}"]\n{sensors}[local_cache]\nenabled = false\n'
            "[hello]\nenabled = true\nrate_hz = 10\n"
        )
        proc = robot(tmp, "robot1", text)
        settle(3.0)
        assert proc.interrupt() == 0, proc.output()
        settle(0.5)  # the final report reaches the recorder
        assert recorder.interrupt() == 0, recorder.output()
        assert internal.interrupt() == 0, internal.output()
    return out


def test_an_independent_reader_decodes_every_sensor_topic(every_kind: Path) -> None:
    with every_kind.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
        assert {s.name for s in summary.schemas.values()} == {*SENSORS.values(), DIAGNOSTIC_ARRAY}
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        channels = {c.topic: c for c in summary.channels.values()}
        assert {c.message_encoding for c in channels.values()} == {"cdr"}
        # one channel per key: 9 sensors, and the robot's announce, stats, presence and mode;
        # the Hello probe (no ROS 2 type) is left out
        assert set(channels) == {f"/robot1/{name}" for name in SENSORS} | {
            "/robot1/arpz/announce",
            "/robot1/arpz/stats",
            "/robot1/arpz/presence",
            "/robot1/arpz/mode/channel",
        }
        for name in SENSORS:
            metadata = channels[f"/robot1/{name}"].metadata
            where = "frames" if name in ("cam", "cloud") else "sensor"
            assert metadata["arpz_key"] == f"arpz/itest/robot/robot1/{where}/{name}"
            assert "reliability: 1" in metadata["offered_qos_profiles"]  # RELIABLE
            assert json.loads(metadata["arpz_qos"])["reliability"] == "reliable"
        decoded: dict[str, list[Any]] = {}
        for schema, channel, message, ros in reader.iter_decoded_messages(
            topics=[f"/robot1/{name}" for name in SENSORS]
        ):
            assert schema.name == SENSORS[channel.topic.rsplit("/", 1)[1]]
            if hasattr(ros, "header"):  # the robot's stamp is the log time
                stamp = ros.header.stamp
                assert message.log_time == stamp.sec * 10**9 + stamp.nanosec
            assert message.publish_time >= message.log_time  # arrival after the robot's stamp
            decoded.setdefault(channel.topic, []).append(ros)
    scan = decoded["/robot1/lidar"][0]
    assert (
        len(scan.ranges) == 1
        and 0.5 < scan.ranges[0] < 10
        and scan.header.frame_id == "robot1/lidar"
    )
    assert all(18 <= m.temperature <= 30 for m in decoded["/robot1/dht11"])
    assert all(8 < m.linear_acceleration.z < 12 for m in decoded["/robot1/imu"])
    assert all(m.radiation_type == 0 and 0.5 < m.range < 2 for m in decoded["/robot1/ultrasonic"])
    assert {m.illuminance for m in decoded["/robot1/light"]} <= {0.0, 100.0}
    image = decoded["/robot1/cam"][0]
    assert (image.width, image.height, image.encoding, len(image.data)) == (64, 48, "rgb8", 9216)
    cloud = decoded["/robot1/cloud"][0]
    assert (cloud.width, cloud.point_step, len(cloud.data)) == (100, 12, 1200)
    xyz = np.frombuffer(bytes(cloud.data), dtype="<f4").reshape(-1, 3)
    assert np.all(np.hypot(xyz[:, 0], xyz[:, 1]) > 1.5)  # the simulated room's walls: 2..6 m


def test_mcap_ros2_support_reads_the_whole_file(every_kind: Path) -> None:
    """No topic filter: every channel, the robot's reports and tokens included, decodes."""
    decoded = read_ros2_whole(every_kind)
    assert len(decoded) == message_count(every_kind) > 300
    by_topic: dict[str, list[Any]] = {}
    for message in decoded:
        by_topic.setdefault(message.channel.topic, []).append(message.ros_msg)
    [presence] = by_topic["/robot1/arpz/presence"][:1]
    assert presence.status[0].name == "robot1/presence"
    assert {kv.key: kv.value for kv in presence.status[0].values} == {"alive": "true"}
    announce = by_topic["/robot1/arpz/announce"][0].status[0]
    values = {kv.key: kv.value for kv in announce.values}
    assert {values[f"sensors[{i}].topic"] for i in range(9)} == set(SENSORS)
    assert announce.hardware_id == "robot1"
    final = [s.status[0] for s in by_topic["/robot1/arpz/stats"] if "final" in s.status[0].message]
    assert len(final) == 1 and final[0].level == 0


def test_the_hello_probe_is_left_out_and_counted(every_kind: Path) -> None:
    summary = json.loads(every_kind.with_suffix(".json").read_text())
    left_out = summary["internal_left_out"]
    assert left_out["/robot1/hello"] >= 10 and left_out["/robot1/cmd/hello"] >= 10


def test_include_internal_keeps_the_hello_probe_as_json(every_kind: Path) -> None:
    """The --include-internal file: every message of it read by the mcap library, each CDR one
    decoded as a ROS 2 message and each JSON one by a JSON decoder; rosbags still reads every
    CDR message of it (the JSON channels are schemaless, which it lists and skips)."""
    from rosbags.highlevel import AnyReader

    internal = every_kind.with_name("internal.mcap")
    count = 0
    encodings: dict[str, set[str]] = {}
    hellos: dict[str, list[Any]] = {}
    with internal.open("rb") as stream:
        for schema, channel, message in make_reader(stream).iter_messages():
            count += 1
            encodings.setdefault(channel.message_encoding, set()).add(
                schema.encoding if schema else "schemaless"
            )
            if channel.message_encoding == "json":
                hellos.setdefault(channel.topic, []).append(json.loads(message.data))
            else:
                assert schema is not None
                deserialize(message.data, schema.name)
    assert count == message_count(internal)
    assert encodings == {"cdr": {"ros2msg"}, "json": {"schemaless"}}
    assert set(hellos) == {"/robot1/hello", "/robot1/cmd/hello"}
    assert {h["stage"] for h in hellos["/robot1/hello"]} <= {0, 2}
    assert {h["stage"] for h in hellos["/robot1/cmd/hello"]} <= {1, 3}
    assert all(h["origin"] == "robot1" for h in hellos["/robot1/hello"])
    cdr_count = count - sum(len(h) for h in hellos.values())
    with AnyReader([internal]) as bag:
        cdr = [c for c in bag.connections if c.msgtype != "__schemaless__"]
        assert len(cdr) == len(bag.connections) - 2
        decoded = [bag.deserialize(raw, c.msgtype) for c, _, raw in bag.messages(connections=cdr)]
        assert len(decoded) == cdr_count
    summary = json.loads(internal.with_suffix(".json").read_text())
    assert summary["internal_left_out"] == {} and summary["include_internal"]


def test_the_counts_match_the_robots_own_counters(every_kind: Path) -> None:
    recorded = messages(every_kind)
    stats = [message_from_cdr(RobotStats, m.data) for _, _, m in recorded["/robot1/arpz/stats"]]
    final = [s for s in stats if s.final]
    assert len(final) == 1, "the robot's final report is in the recording"
    summary = json.loads(every_kind.with_suffix(".json").read_text())
    for name in SENSORS:
        topic = f"/robot1/{name}"
        sent = final[0].topics[name].sent
        assert sent >= 20, name
        assert summary["topics"][topic]["lost"] == 0, name
        # every sample the robot sent during the recording is in the file, once
        assert len(recorded[topic]) == summary["topics"][topic]["messages"] == sent, name
        seqs = [m.sequence for _, _, m in recorded[topic]]
        assert sorted(seqs) == list(range(1, sent + 1)), name


def test_rosbags_opens_the_recording_as_a_rosbag2(every_kind: Path) -> None:
    """rosbags' rosbag2 Reader and its AnyReader (which types the messages from the file's own
    definitions) decode every message of every connection."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    counts: dict[str, int] = {}
    with Reader(every_kind) as bag:
        by_topic = {c.topic: c for c in bag.connections}
        assert by_topic["/robot1/lidar"].msgtype == "sensor_msgs/msg/LaserScan"
        assert by_topic["/robot1/arpz/stats"].msgtype == DIAGNOSTIC_ARRAY
        assert by_topic["/robot1/cam"].ext.offered_qos_profiles[0].depth == 1  # frames_qos
        assert {c.ext.serialization_format for c in bag.connections} == {"cdr"}
        for connection, _, raw in bag.messages():
            store.deserialize_cdr(raw, connection.msgtype)
            counts[connection.topic] = counts.get(connection.topic, 0) + 1
    recorded = messages(every_kind)
    assert counts == {topic: len(items) for topic, items in recorded.items()}
    any_counts: dict[str, int] = {}
    with AnyReader([every_kind]) as bag:
        for connection, _, raw in bag.messages():
            bag.deserialize(raw, connection.msgtype)
            any_counts[connection.topic] = any_counts.get(connection.topic, 0) + 1
    assert any_counts == counts


# -- record, play, same decisions ----------------------------------------------------------------

MISSION = '[mission]\nworld = "hallway_small"\ntime_limit_s = 60\n'
#: the recording runs until the leader's first corner is done (about 6.5 s after the start on an
#: idle host: 4.5 s to the corner, 2 s of turning), then AFTER_TURN_S more; a slowed host once
#: took over 12 s to the corner, so the recording's length follows the mission, not a constant
AFTER_TURN_S = 1.0
#: the longest a slow host may take to finish the first corner before the test fails
TURN_TIMEOUT_S = 60.0
#: the replay takes as long as the recording: the bound on waiting for play
PLAY_TIMEOUT_S = TURN_TIMEOUT_S + 30.0


def commands(path: Path) -> dict[str, list[tuple[int, tuple[float, float]]]]:
    """robot -> [(stamp_ns, (v, omega))] of the CEDDP's velocity commands in a recording: each
    a geometry_msgs/msg/Twist whose log time is the command's stamp."""
    out: dict[str, list[tuple[int, tuple[float, float]]]] = {}
    for topic, items in messages(path).items():
        if topic.endswith("/cmd/velocity"):
            for schema, _, message in items:
                assert schema.name == "geometry_msgs/msg/Twist"
                twist = deserialize(message.data, schema.name)
                out.setdefault(topic.split("/")[1], []).append(
                    (message.log_time, (twist.linear.x, twist.angular.z))
                )
    return out


def replay_offset_ns(original: Path, replay: Path) -> int:
    """How much later the replay ran than the original: play shifts every stamp by one constant
    (at --rate 1), measured here on the leader's front beam, which both files hold."""
    first = [messages(path)["/robot1/lidar_0"][0][2].log_time for path in (original, replay)]
    return first[1] - first[0]


#: how far (ns) a replayed decision may sit from the recorded one: 3 planner ticks of 50 ms
SLACK_NS = 150_000_000

HOLD = (0.0, 0.0)

#: a command turning at least this fast (rad/s) is part of a corner turn, not lane keeping
TURNING_RAD_S = 0.5
#: turning commands that must be compared (2 s of turning at 20 Hz make about 40)
MIN_TURNING = 5


def compare(
    recorded: list[tuple[int, tuple[float, float]]],
    replayed: list[tuple[int, tuple[float, float]]],
    offset_ns: int,
) -> tuple[int, int, int, int]:
    """(commands compared, commands equal, holds skipped, turning commands compared): each
    recorded command from the start
    of motion on against the replayed commands within SLACK_NS of it on the replay's time line
    (its stamp + offset); equal when one of them is (v exactly, omega within 0.01 rad/s).

    A hold (the fleet stopped because a beam arrived late: the staleness rule) is a reaction to
    the machine's timing, not a decision taken on the data, so a recorded command is not
    compared where either run held (counted as skipped); commands beyond either end are not
    compared either."""
    start = next(s for s, (v, _) in recorded if v > 0)
    times = [s - offset_ns for s, _ in replayed]
    compared = equal = skipped = turning = 0
    for stamp, (v, omega) in recorded:
        lo = bisect.bisect_left(times, stamp - SLACK_NS)
        hi = bisect.bisect_right(times, stamp + SLACK_NS)
        near = [replayed[k][1] for k in range(lo, hi)]
        if stamp < start or not near:
            continue
        if (v, omega) == HOLD or HOLD in near:
            skipped += 1
            continue
        compared += 1
        turning += abs(omega) >= TURNING_RAD_S
        equal += any(v_b == v and abs(omega_b - omega) <= 0.01 for v_b, omega_b in near)
    return compared, equal, skipped, turning


# a mission in real time at 20 Hz: beside another integration test it fell short of its command
# count (98 where 104 were required); runs with the machine to itself (tests/conftest.py)
@pytest.mark.cpu_exclusive(whole_machine=True)
def test_a_replayed_mission_makes_the_same_planner_decisions(tmp_path: Path) -> None:
    """The hallway mission's 3 robots are recorded, with the CEDDP's commands, until the leader's
    first corner is done, then played into a fresh CEDDP running the same planner; its commands
    are recorded too.

    Tolerance: the replay CEDDP's 20 Hz planner ticks fall at another phase than the original's
    relative to the beams' arrivals, so a decision taken on a beam that arrived between two ticks
    can move by a tick or two, and on a loaded machine either run can hold the fleet for a few
    ticks when a beam is late (a "stale" stop, the staleness rule, not a decision on the data).
    Hence: each recorded command from the start of motion on is compared with the replayed
    commands within 3 ticks of it on the replay's time line (play shifts all stamps by one
    constant, measured on a beam both files hold), where neither run held; at least 95 % must
    be equal (v exactly, omega within 0.01 rad/s). How many holds a run has is the host's
    timing, so what is bounded is what remains: at least a quarter of the nominal 20 Hz
    decisions compared, MIN_TURNING of them turning, so the decisions compared include more
    than driving straight."""
    original, replay = tmp_path / "original.mcap", tmp_path / "replay.mcap"
    first = tmp_path / "first"
    first.mkdir()
    with ceddp(first, extra=MISSION) as (server, endpoint):
        recorder = record(endpoint, original, first)
        fleet = [
            robot(
                first,
                f"robot{i}",
                f'connect = ["{endpoint}"]\nseed = {i}\n[sim]\nworld = "hallway_small"\n',
            )
            for i in (1, 2, 3)
        ]
        try:
            server.wait_for("mission turn_done", timeout_s=TURN_TIMEOUT_S)
            time.sleep(AFTER_TURN_S)  # deliberately: the turn's last commands are recorded too
            assert recorder.interrupt() == 0, recorder.output()
        finally:
            for proc in fleet:
                proc.kill()
    recorded_s = json.loads(original.with_suffix(".json").read_text())["duration_s"]
    second = tmp_path / "second"
    second.mkdir()
    with ceddp(second, extra=MISSION) as (_, endpoint):
        recorder = record(endpoint, replay, second, "*/cmd/*", "/robot1/lidar_0")
        play = Process(
            "play",
            ["-m", "arpz.tools.play", str(original), "--connect", endpoint],
            second,
        )
        play.popen.wait(timeout=PLAY_TIMEOUT_S)
        assert play.popen.returncode == 0, play.output()
        assert "published" in play.output()
        assert recorder.interrupt() == 0, recorder.output()
    before, after = commands(original), commands(replay)
    offset_ns = replay_offset_ns(original, replay)
    assert sorted(before) == sorted(after) == ["robot1", "robot2", "robot3"]
    for name in before:
        assert any(abs(omega) >= TURNING_RAD_S for _, (_, omega) in before[name]), "no turn"
        compared, equal, skipped, turning = compare(before[name], after[name], offset_ns)
        figures = (name, compared, equal, skipped, turning, recorded_s)
        # 20 Hz over the recording, less the start. The planner's rate is the CPU it gets: on a
        # VM slowed fourfold by a neighbour, 98 and 90 commands came where 104 were asked, so
        # half the nominal count is required
        assert compared + skipped >= 0.5 * recorded_s * 20, figures
        # Holds for late beams are the host's timing: idle, none (0-3 of 150 skipped); in CI on
        # a slow host 71 of 173 (each hold skips the recorded commands within SLACK_NS of it).
        # What must remain is enough decisions to compare, a turn among them
        assert compared >= 0.25 * recorded_s * 20, figures
        assert turning >= MIN_TURNING, figures
        assert equal >= 0.95 * compared, figures


def test_the_camera_replay_driver_sends_the_recorded_frames(every_kind: Path) -> None:
    from arpz.tools.frame_replay import CameraReplay

    with every_kind.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        recorded = [
            (message.log_time, bytes(image.data))
            for _, _, message, image in reader.iter_decoded_messages(topics=["/robot1/cam"])
        ]
    driver = CameraReplay({"recording": str(every_kind), "topic": "/robot1/cam"}, seed=0)
    first = recorded[0][0]
    assert [driver.read((t - first) / 1e9) for t, _ in recorded] == [f for _, f in recorded]
