"""``arpz record`` and ``arpz play`` over the in-memory bus: what goes into the MCAP file, how it
is split, and what play publishes back (the real-router tests are
tests/integration/test_record_play.py)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import msgspec
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer as McapWriter
from mcap_ros2.decoder import DecoderFactory
from rosbags.rosbag2.metadata import parse_qos

from arpz.channel.io import Inlet, Outlet
from arpz.core import keys
from arpz.core.config import TrafficQos
from arpz.core.messages import (
    ANNOUNCE_DECODER,
    HELLO_DECODER,
    SAMPLE_DECODER,
    Announce,
    CeddpStats,
    Command,
    Hello,
    Sample,
    TopicInfo,
    encode,
)
from arpz.core.protocol.qos import DurabilityPolicy, QosProfile, ReliabilityPolicy
from arpz.core.rosmsg.commands import TWIST
from arpz.tools import record as record_tool
from arpz.tools._recording import (
    MSGPACK,
    McapSink,
    Topic,
    offered_qos_yaml,
    split_path,
)
from arpz.tools.play import Player, RecordingError, recording_files
from arpz.tools.record import Recorder
from arpz.transport.memory import MemoryBus, MemoryTransport
from tests.support import wait_until

FLEET = "t"
TRAFFIC = TrafficQos()


@pytest.fixture
def bus() -> Iterator[MemoryBus]:
    yield MemoryBus()


class FakeRobot:
    """What a robot agent puts on the wire, with the same Outlets and keys."""

    def __init__(self, transport: MemoryTransport, name: str = "robot1", mode: str = "channel"):
        self.transport, self.name = transport, name
        channel = mode == "channel"
        self.tokens = [
            transport.declare_token(keys.presence_key(FLEET, name)),
            transport.declare_token(keys.robot_mode_key(FLEET, name, mode)),
        ]
        self.announce = Outlet(
            transport, keys.announce_key(FLEET, name), TRAFFIC.report_qos if channel else None
        )
        self.outlets = {
            topic: Outlet(
                transport,
                keys.sensor_key(FLEET, name, topic),
                TRAFFIC.sensor_qos if channel else None,
            )
            for topic in ("lidar", "pir")
        }
        self.seqs = {"lidar": 0, "pir": 0}

    def send_announce(self) -> None:
        message = Announce(
            robot=self.name,
            incarnation="abc",
            sensors=[
                TopicInfo("lidar", "lidar", 10.0, "float"),
                TopicInfo("pir", "pir", 10.0, "str"),
            ],
            commands=["hello", "velocity"],
        )
        self.announce.send(encode(message), time.time_ns())

    def send(self, topic: str, value: float | str, *, skip: int = 0) -> Sample:
        self.seqs[topic] += 1 + skip
        sample = Sample(f"{self.name}:abc", self.seqs[topic], time.time_ns(), value)
        self.outlets[topic].send(encode(sample), sample.stamp_ns)
        return sample


def recorder(bus: MemoryBus, out: Path, **kwargs: object) -> Recorder:
    sink = McapSink(out, split_bytes=0, split_s=0.0, metadata={"fleet": FLEET})
    rec = Recorder(MemoryTransport(bus), FLEET, sink, mode="channel", **kwargs)  # type: ignore[arg-type]
    rec.start()
    return rec


def run_until(rec: Recorder, done: object) -> None:
    stop = threading.Event()
    thread = threading.Thread(target=rec.run, args=(stop,))
    thread.start()
    try:
        wait_until(done, what="the recording")  # type: ignore[arg-type]
    finally:
        stop.set()
        thread.join()


def by_topic(path: Path) -> dict[str, list[tuple[object, object]]]:
    out: dict[str, list[tuple[object, object]]] = {}
    with path.open("rb") as stream:
        for _, channel, message in make_reader(stream).iter_messages(log_time_order=True):
            out.setdefault(channel.topic, []).append((channel, message))
    return out


def test_every_channel_is_a_standard_ros2_type_by_default(bus: MemoryBus, tmp_path: Path) -> None:
    """Sensor topics, commands, reports and tokens are all CDR of standard ROS 2 types, so
    mcap-ros2-support reads the whole file with no topic filter; the Hello probe (no ROS 2
    type) is left out and counted."""
    out = tmp_path / "r.mcap"
    rec = recorder(bus, out)
    robot = FakeRobot(MemoryTransport(bus))
    robot.send_announce()
    wait_until(lambda: all(o.matched for o in robot.outlets.values()), what="matching")
    sent = [robot.send("lidar", 2.37), robot.send("lidar", 2.38), robot.send("pir", "detect")]
    command = Command("ceddp:1", 1, time.time_ns(), [0.8, -0.25])
    ceddp = Outlet(
        MemoryTransport(bus), keys.command_key(FLEET, "robot1", "velocity"), TRAFFIC.command_qos
    )
    hello = Outlet(
        MemoryTransport(bus), keys.sensor_key(FLEET, "robot1", keys.HELLO), TRAFFIC.sensor_qos
    )
    wait_until(lambda: ceddp.matched and hello.matched, what="the command and Hello readers")
    ceddp.send(encode(command), command.stamp_ns)
    hello.send(encode(Hello("robot1:abc", 1, time.time_ns(), "robot1", 1, 1, 0)), time.time_ns())
    run_until(rec, lambda: sum(t.messages for t in rec.tallies.values()) >= 7 and rec.left_out)
    files = rec.close()
    assert files == [out]
    topics = by_topic(out)
    assert set(topics) == {
        "/robot1/lidar",
        "/robot1/pir",
        "/robot1/cmd/velocity",
        "/robot1/arpz/announce",
        "/robot1/arpz/presence",
        "/robot1/arpz/mode/channel",
    }
    assert {c.message_encoding for c, _ in (v[0] for v in topics.values())} == {"cdr"}  # type: ignore[attr-defined]
    channel, message = topics["/robot1/lidar"][0]
    assert channel.metadata["arpz_key"] == "arpz/t/robot/robot1/sensor/lidar"  # type: ignore[attr-defined]
    assert message.log_time == sent[0].stamp_ns and message.sequence == 1  # type: ignore[attr-defined]
    assert message.publish_time >= message.log_time  # type: ignore[attr-defined]
    with out.open("rb") as stream:  # the whole file, no topic filter
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        decoded = {c.topic: (s, m, ros) for s, c, m, ros in reader.iter_decoded_messages()}
    schema, message, twist = decoded["/robot1/cmd/velocity"]
    assert schema.name == TWIST  # type: ignore[union-attr]
    assert (twist.linear.x, twist.angular.z) == (0.8, -0.25)
    assert message.log_time == command.stamp_ns and message.sequence == 1
    schema, _, announce = decoded["/robot1/arpz/announce"]
    assert schema.name == "diagnostic_msgs/msg/DiagnosticArray"  # type: ignore[union-attr]
    values = {kv.key: kv.value for kv in announce.status[0].values}
    assert values["sensors[0].kind"] == "lidar" and values["commands[1]"] == "velocity"
    assert announce.status[0].hardware_id == "robot1"
    assert decoded["/robot1/arpz/presence"][2].status[0].values[0].value == "true"
    summary = rec.summary()
    assert summary["topics"]["/robot1/lidar"]["messages"] == 2
    assert summary["lost"] == 0
    assert summary["internal_left_out"] == {"/robot1/hello": 1}
    text = record_tool.format_summary(summary)
    assert "sensor_msgs/msg/LaserScan" in text and "--include-internal" in text


def test_include_internal_keeps_arpz_messages_as_json(bus: MemoryBus, tmp_path: Path) -> None:
    """The Hello probe and the samples of a topic no announcement named: schemaless JSON
    channels, each message the object of the arpz message's fields."""
    rec = recorder(bus, tmp_path / "r.mcap", include_internal=True)
    robot = FakeRobot(MemoryTransport(bus))  # no announcement
    hello = Outlet(
        MemoryTransport(bus), keys.sensor_key(FLEET, "robot1", keys.HELLO), TRAFFIC.sensor_qos
    )
    wait_until(lambda: robot.outlets["lidar"].matched and hello.matched, what="matching")
    sample = robot.send("lidar", 1.0)
    probe = Hello("robot1:abc", 1, time.time_ns(), "robot1", 1, 1, 0)
    hello.send(encode(probe), probe.stamp_ns)
    run_until(rec, lambda: not rec._queue.qsize() and rec._pending and rec.tallies)
    rec.close()  # what still waits for an announcement is written as it came
    topics = by_topic(tmp_path / "r.mcap")
    channel, message = topics["/robot1/lidar"][0]
    assert channel.message_encoding == "json"  # type: ignore[attr-defined]
    assert channel.metadata["arpz_type"] == "arpz.core.messages.Sample"  # type: ignore[attr-defined]
    assert msgspec.json.decode(message.data) == msgspec.to_builtins(  # type: ignore[attr-defined]
        {"writer": sample.writer, "seq": 1, "stamp_ns": sample.stamp_ns, "value": 1.0}
    ) | {"changed_ns": 0, "since_ns": 0}
    channel, message = topics["/robot1/hello"][0]
    assert msgspec.json.decode(message.data)["origin"] == "robot1"  # type: ignore[attr-defined]
    # schemaless (rosbags refuses a whole file with a jsonschema schema), the JSON Schema in
    # the channel's metadata
    assert channel.schema_id == 0  # type: ignore[attr-defined]
    schema = msgspec.json.decode(channel.metadata["arpz_json_schema"])  # type: ignore[attr-defined]
    assert schema["$defs"]["Hello"]["type"] == "object"
    assert list(schema["$defs"]["Hello"]["properties"])[:3] == ["writer", "seq", "stamp_ns"]
    assert rec.summary()["internal_left_out"] == {}


def test_a_topic_never_announced_is_left_out_and_counted(bus: MemoryBus, tmp_path: Path) -> None:
    rec = recorder(bus, tmp_path / "r.mcap")
    robot = FakeRobot(MemoryTransport(bus))  # no announcement
    wait_until(lambda: robot.outlets["lidar"].matched, what="matching")
    robot.send("lidar", 1.0)
    run_until(rec, lambda: not rec._queue.qsize() and rec._pending)
    rec.close()
    assert "/robot1/lidar" not in by_topic(tmp_path / "r.mcap")
    assert rec.summary()["internal_left_out"] == {"/robot1/lidar": 1}


def test_patterns_select_topics_but_never_the_announcements(bus: MemoryBus, tmp_path: Path) -> None:
    rec = recorder(bus, tmp_path / "r.mcap", patterns=["/robot1/pir"])
    robot = FakeRobot(MemoryTransport(bus))
    robot.send_announce()
    wait_until(lambda: all(o.matched for o in robot.outlets.values()), what="matching")
    robot.send("lidar", 1.0)
    robot.send("pir", "detect")
    run_until(rec, lambda: "arpz/t/robot/robot1/sensor/pir" in rec.tallies)
    rec.close()
    assert set(by_topic(tmp_path / "r.mcap")) == {
        "/robot1/pir",
        "/robot1/arpz/announce",
        "/robot1/arpz/presence",
        "/robot1/arpz/mode/channel",
    }
    assert rec.summary()["skipped_by_pattern"] == 1


def test_plain_mode_counts_losses_from_the_payload_seq(bus: MemoryBus, tmp_path: Path) -> None:
    sink = McapSink(tmp_path / "r.mcap", split_bytes=0, split_s=0.0, metadata={})
    rec = Recorder(MemoryTransport(bus), FLEET, sink, mode_wait_s=0.2)
    robot = FakeRobot(MemoryTransport(bus), mode="none")
    rec.start()  # decides the mode from the robot's token (no CEDDP here)
    assert rec.mode == "none"
    robot.send_announce()
    robot.send("lidar", 1.0)
    robot.send("lidar", 1.1, skip=2)  # seq 4 after seq 1: two lost
    run_until(rec, lambda: "arpz/t/robot/robot1/sensor/lidar" in rec.tallies)
    rec.close()
    lidar = rec.summary()["topics"]["/robot1/lidar"]
    assert (lidar["messages"], lidar["lost"]) == (2, 2)
    channel, _ = by_topic(tmp_path / "r.mcap")["/robot1/lidar"][0]
    assert channel.metadata["arpz_qos"] == "none"  # type: ignore[attr-defined]


def test_a_recording_is_split_by_size_and_every_part_is_whole(tmp_path: Path) -> None:
    out = tmp_path / "big.mcap"
    topic = Topic("arpz/t/robot/r/sensor/lidar", "r", "lidar", TRAFFIC.sensor_qos)
    from arpz.core.rosmsg.convert import to_cdr

    with McapSink(out, split_bytes=4000, split_s=0.0, metadata={}) as sink:
        for i in range(400):
            data = to_cdr("lidar", 1.0 + i / 100, stamp_ns=i, frame_id="r/lidar")
            sink.write(topic, data, log_ns=i, publish_ns=i, sequence=i)
    assert len(sink.files) > 1
    assert sink.files[0] == tmp_path / "big_0.mcap" == split_path(out, 0, True)
    assert recording_files(out) == sink.files
    total = 0
    for path in sink.files:
        with path.open("rb") as stream:
            summary = make_reader(stream).get_summary()
        assert summary is not None and summary.statistics is not None
        assert [s.name for s in summary.schemas.values()] == ["sensor_msgs/msg/LaserScan"]
        total += summary.statistics.message_count
    assert total == 400


def test_split_by_duration_of_log_time(tmp_path: Path) -> None:
    topic = Topic("arpz/t/robot/r/cmd/velocity", "r", "command", TRAFFIC.command_qos)
    with McapSink(tmp_path / "d.mcap", split_bytes=0, split_s=1.0, metadata={}) as sink:
        for i in range(5):
            sink.write(topic, b"\x90", log_ns=i * 600_000_000, publish_ns=0, sequence=0)
    assert [p.name for p in sink.files] == ["d_0.mcap", "d_1.mcap", "d_2.mcap"]


def test_offered_qos_profiles_read_back_as_rosbag2_qos() -> None:
    qos = QosProfile(depth=4, durability=DurabilityPolicy.TRANSIENT_LOCAL, lifespan_s=0.5)
    [parsed] = parse_qos(offered_qos_yaml(qos))
    assert (parsed.history.name, parsed.depth) == ("KEEP_LAST", 4)
    assert (parsed.reliability.name, parsed.durability.name) == ("RELIABLE", "TRANSIENT_LOCAL")
    assert (parsed.lifespan.sec, parsed.lifespan.nsec) == (0, 500_000_000)
    assert parsed.deadline.sec == 2**31 - 1  # arpz's 0 (none) is rmw's infinite
    [plain] = parse_qos(offered_qos_yaml(None))
    assert plain.reliability.name == "BEST_EFFORT"
    best_effort = QosProfile(reliability=ReliabilityPolicy.BEST_EFFORT)
    assert parse_qos(offered_qos_yaml(best_effort))[0].reliability.name == "BEST_EFFORT"


def _played(
    bus: MemoryBus, recording: Path, rate: float = 8.0
) -> tuple[list[tuple[str, bytes]], list[tuple[str, bool]]]:
    """What play publishes of ``recording`` into the fleet on ``bus``, read as a CEDDP would:
    (key, payload) of every message and (key, alive) of every presence token change."""
    listener = MemoryTransport(bus)
    got: list[tuple[str, bytes]] = []
    alive: list[tuple[str, bool]] = []
    lock = threading.Lock()

    def on_message(key: str, payload: bytes) -> None:
        with lock:
            got.append((key, payload))

    inlets = [
        Inlet(listener, keys.all_sensors(FLEET), TRAFFIC.sensor_qos, on_message),
        Inlet(listener, keys.all_reports(FLEET), TRAFFIC.report_qos, on_message),
    ]
    listener.watch_liveliness(keys.all_presence(FLEET), lambda k, a: alive.append((k, a)))
    player = Player(MemoryTransport(bus), recording_files(recording), rate=rate)
    player.open(match_timeout_s=2.0)
    player.run(threading.Event())
    player.close()
    wait_until(lambda: len(got) >= player.summary()["published"], what="the replayed messages")
    for inlet in inlets:
        inlet.close()
    return got, alive


def test_play_publishes_the_recording_as_the_robot_did(bus: MemoryBus, tmp_path: Path) -> None:
    out = tmp_path / "r.mcap"
    rec = recorder(bus, out)
    robot = FakeRobot(MemoryTransport(bus))
    robot.send_announce()
    wait_until(lambda: all(o.matched for o in robot.outlets.values()), what="matching")
    sent = [robot.send("lidar", 2.37), robot.send("pir", "detect"), robot.send("lidar", 2.5)]
    run_until(rec, lambda: sum(t.messages for t in rec.tallies.values()) >= 6)
    rec.close()
    for token in robot.tokens:
        token.undeclare()

    started_ns = time.time_ns()
    got, alive = _played(MemoryBus(), out, rate=4.0)  # into a new fleet
    announce = [ANNOUNCE_DECODER.decode(p) for k, p in got if k.endswith("/announce")]
    assert announce and announce[0].incarnation != "abc"  # a replay is a new incarnation
    samples = [SAMPLE_DECODER.decode(p) for k, p in got if "/sensor/" in k]
    assert [s.value for s in samples] == [s.value for s in sent]
    assert [s.seq for s in samples] == [1, 1, 2]  # numbered by the replay's writer, per key
    assert all(s.stamp_ns >= started_ns for s in samples)  # re-stamped into the replay's time
    # at x4 the gaps between the recorded stamps shrink fourfold
    recorded_gap = sent[2].stamp_ns - sent[0].stamp_ns
    assert samples[2].stamp_ns - samples[0].stamp_ns == pytest.approx(recorded_gap / 4, abs=2)
    assert ("arpz/t/robot/robot1/presence", True) in alive
    assert alive[-1] == ("arpz/t/robot/robot1/presence", False)  # the robot left at the end
    assert len(got) == 4  # the announcement and the three samples


def test_play_says_what_is_wrong_with_a_file(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="no such recording"):
        recording_files(tmp_path / "none.mcap")
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"not mcap")
    with pytest.raises(RecordingError, match="not a readable MCAP file"):
        Player(MemoryTransport(MemoryBus()), [bad])


def test_the_command_line_refuses_bad_options(capsys: pytest.CaptureFixture[str]) -> None:
    assert record_tool.main(["--out", "x.txt", "--connect", "tcp/127.0.0.1:1"]) == 2
    assert "give a file name ending in .mcap" in capsys.readouterr().err
    assert record_tool.main(["--out", "x.mcap", "--camera-size", "wide"]) == 2
    assert "WIDTHxHEIGHT" in capsys.readouterr().err
    assert record_tool.main(["--out", "x.mcap", "--connect", "foo"]) == 2
    assert "arpz record: error: " in capsys.readouterr().err


def test_play_topics_select_what_is_played_and_which_robots(bus: MemoryBus, tmp_path: Path) -> None:
    out = tmp_path / "r.mcap"
    rec = recorder(bus, out)
    robot = FakeRobot(MemoryTransport(bus))
    robot.send_announce()
    wait_until(lambda: all(o.matched for o in robot.outlets.values()), what="matching")
    robot.send("lidar", 1.0)
    robot.send("pir", "detect")
    run_until(rec, lambda: sum(t.messages for t in rec.tallies.values()) >= 5)
    rec.close()
    some = Player(MemoryTransport(MemoryBus()), [out], patterns=["/robot1/pir"])
    some.open(match_timeout_s=0.0)
    assert set(some.summary()["topics"]) == {"/robot1/pir", "/robot1/arpz/announce"}
    none = Player(MemoryTransport(MemoryBus()), [out], patterns=["/robot9/*"])
    none.open(match_timeout_s=0.0)
    assert none.summary()["robots"] == [] and none.summary()["topics"] == {}


def test_channel_losses_are_counted_on_the_topic_of_their_writer(tmp_path: Path) -> None:
    """MESSAGE_LOST names a writer guid; the recorder learned each guid's key from its samples
    (a guid it never got a sample from is still counted, as unattributed)."""
    from arpz.core.protocol.events import DataInfo, MessageLostStatus

    sink = McapSink(tmp_path / "r.mcap", split_bytes=0, split_s=0.0, metadata={})
    rec = Recorder(MemoryTransport(MemoryBus()), FLEET, sink, mode="channel")
    rec.kinds[("robot1", "lidar")] = "lidar"
    key = keys.sensor_key(FLEET, "robot1", "lidar")
    sample = Sample("robot1:abc", 5, time.time_ns(), 1.5)
    rec._data_callback("sensor")(encode(sample), DataInfo(key, "g1", 5, sample.stamp_ns))
    rec._on_lost(MessageLostStatus(total_count=3, total_count_change=3, writer="g1"))
    rec._on_lost(MessageLostStatus(total_count=1, total_count_change=1, writer="g-unknown"))
    rec.close()
    summary = rec.summary()
    assert summary["topics"]["/robot1/lidar"]["lost"] == 3
    assert (summary["unattributed_lost"], summary["lost"]) == (1, 4)


def test_the_recorded_qos_can_be_the_fleets_own(tmp_path: Path) -> None:
    """--qos-from: a CEDDP's config (or a robot's) gives the profiles the recorder reads with
    and stores; a file that is neither is refused naming the field."""
    from arpz.core.config import ConfigError
    from arpz.tools.record import _fleet_traffic

    ceddp = tmp_path / "ceddp.toml"
    ceddp.write_text('fleet = "f"\n[sensor_qos]\ndepth = 7\nhistory = "keep_last"\n')
    traffic = _fleet_traffic(ceddp)
    assert traffic is not None and traffic.sensor_qos.depth == 7
    robot = tmp_path / "robot.toml"
    robot.write_text('robot_id = "r1"\n[command_qos]\ndepth = 3\n')
    traffic = _fleet_traffic(robot)
    assert traffic is not None and traffic.command_qos.depth == 3
    assert _fleet_traffic(None) is None
    bad = tmp_path / "bad.toml"
    bad.write_text('fleet = "f"\n[sensor_qos]\ndepth = "deep"\n')
    with pytest.raises(ConfigError, match=r"sensor_qos\.depth"):
        _fleet_traffic(bad)


def test_play_reads_the_internal_json_channels(bus: MemoryBus, tmp_path: Path) -> None:
    """A recording with --include-internal: the Hello probes (JSON) are played back, as the
    announcement (a DiagnosticArray) and the sensor samples (CDR) are."""
    out = tmp_path / "r.mcap"
    rec = recorder(bus, out, include_internal=True)
    robot = FakeRobot(MemoryTransport(bus))
    hello = Outlet(
        MemoryTransport(bus), keys.sensor_key(FLEET, "robot1", keys.HELLO), TRAFFIC.sensor_qos
    )
    robot.send_announce()
    wait_until(lambda: robot.outlets["lidar"].matched and hello.matched, what="matching")
    robot.send("lidar", 2.5)
    hello.send(encode(Hello("robot1:abc", 1, time.time_ns(), "robot1", 9, 5, 0)), time.time_ns())
    run_until(rec, lambda: "arpz/t/robot/robot1/sensor/hello" in rec.tallies)
    rec.close()
    got, _ = _played(MemoryBus(), out)
    [probe] = [HELLO_DECODER.decode(p) for k, p in got if k.endswith("/sensor/hello")]
    assert (probe.origin, probe.origin_seq, probe.seq) == ("robot1", 9, 1)
    assert probe.writer != "robot1:abc"  # a new incarnation
    assert [SAMPLE_DECODER.decode(p).value for k, p in got if k.endswith("/lidar")] == [2.5]


def test_play_reads_a_recording_made_before_issue_41(tmp_path: Path) -> None:
    """The earlier layout: reports, tokens and raw samples as arpz msgpack on schemaless
    ``msgpack`` channels."""
    old = tmp_path / "old.mcap"
    announce = Announce("robot1", "abc", [TopicInfo("pir", "pir", 10.0, "str")], [])
    sample = Sample("robot1:abc", 4, time.time_ns(), "detect")
    records = [
        ("arpz/t/robot/robot1/presence", "liveliness", None, msgspec.msgpack.encode(True)),
        ("arpz/t/robot/robot1/announce", "announce", TRAFFIC.report_qos, encode(announce)),
        ("arpz/t/robot/robot1/sensor/pir", "sample", TRAFFIC.sensor_qos, encode(sample)),
    ]
    with old.open("wb") as stream:
        writer = McapWriter(stream)
        writer.start(profile="ros2", library="arpz record (before issue 41)")
        writer.add_metadata("arpz", {"fleet": FLEET})
        for i, (key, kind, qos, data) in enumerate(records):
            metadata = {
                "arpz_key": key,
                "arpz_kind": kind,
                "arpz_qos": msgspec.json.encode(qos).decode() if qos else "none",
            }
            channel = writer.register_channel(key, MSGPACK, 0, metadata)
            writer.add_message(channel, log_time=sample.stamp_ns + i, data=data, publish_time=0)
        writer.finish()  # type: ignore[no-untyped-call]
    got, _ = _played(MemoryBus(), old)
    assert [ANNOUNCE_DECODER.decode(p).robot for k, p in got if k.endswith("/announce")] == [
        "robot1"
    ]
    [pir] = [SAMPLE_DECODER.decode(p) for k, p in got if k.endswith("/pir")]
    assert (pir.value, pir.seq) == ("detect", 1)


def test_under_access_control_the_recorder_reads_without_writing(
    bus: MemoryBus, tmp_path: Path
) -> None:
    """The CEDDP says access control is in force: the recorder's readers are BEST_EFFORT (no
    ACKNACK, which an observer's certificate may not send), and it still records."""
    ceddp = MemoryTransport(bus)
    token = ceddp.declare_token(keys.ceddp_mode_key(FLEET, "channel"))
    stats = Outlet(ceddp, keys.ceddp_stats_key(FLEET), None)
    stop = threading.Event()

    def report() -> None:
        while not stop.wait(0.05):
            message = CeddpStats(stamp_ns=time.time_ns(), cpu_percent=1.0, topics=[])
            stats.send(encode(msgspec.structs.replace(message, access_control=True)), 0)

    thread = threading.Thread(target=report)
    thread.start()
    try:
        sink = McapSink(tmp_path / "r.mcap", split_bytes=0, split_s=0.0, metadata={})
        rec = Recorder(MemoryTransport(bus), FLEET, sink, mode_wait_s=1.0, stats_wait_s=2.0)
        rec.start()
    finally:
        stop.set()
        thread.join()
        token.undeclare()
    assert rec.mode == "channel" and rec.read_only
    assert rec.read_only_reason == "the CEDDP reports access control in force"
    assert {r.qos.reliability for r in rec._readers} == {ReliabilityPolicy.BEST_EFFORT}
    robot = FakeRobot(MemoryTransport(bus))
    robot.send_announce()
    wait_until(lambda: robot.outlets["lidar"].matched, what="matching")
    robot.send("lidar", 1.0)
    run_until(rec, lambda: "arpz/t/robot/robot1/sensor/lidar" in rec.tallies)
    rec.close()
    assert rec.summary()["read_only"]
    # the channel kept the fleet's QoS for play, not the recorder's own
    channel, _ = by_topic(tmp_path / "r.mcap")["/robot1/lidar"][0]
    assert msgspec.json.decode(channel.metadata["arpz_qos"])["reliability"] == "reliable"  # type: ignore[attr-defined]
