"""fleet_graph: topic names, the graph built from tokens, announcements and stats, resolving a
topic the user typed, and matching (no Zenoh: observations in, graph out)."""

from __future__ import annotations

from contextlib import closing
from typing import Any

import pytest

from arpz.channel import Writer
from arpz.core import keys
from arpz.core.messages import (
    Announce,
    CeddpStats,
    ClockStats,
    InboundCounters,
    RobotStats,
    TopicCounters,
    TopicInfo,
    encode,
)
from arpz.core.protocol import wire
from arpz.core.protocol.qos import QOS_SENSOR_DATA, QosProfile, encode_match_qos
from arpz.core.traffic import COMMAND_QOS, REPORT_QOS, SENSOR_QOS
from arpz.tools.fleet_graph import (
    CEDDP,
    FleetObserver,
    UnknownTopicError,
    clock_offset,
    discovering,
    matches,
    topic_name,
)
from arpz.tools.topic_text import list_lines
from arpz.transport.memory import MemoryBus, MemoryTransport

F = "f1"


def key(robot: str, rest: str) -> str:
    return f"{keys.robot_prefix(F, robot)}/{rest}"


@pytest.mark.parametrize(
    ("rest", "name"),
    [
        ("robot/r1/sensor/lidar", "/r1/lidar"),
        ("robot/r1/frames/front", "/r1/front"),
        ("robot/r1/sensor/hello", "/r1/hello"),
        ("robot/r1/cmd/velocity", "/r1/cmd/velocity"),
        ("robot/r1/stats", "/r1/stats"),
        ("robot/r1/telemetry", "/r1/telemetry"),
        ("ceddp/stats", "/ceddp/stats"),
        ("ceddp/qos", "/ceddp/qos"),
        ("ceddp/qos/request", "/ceddp/qos/request"),
        ("robot/r1/presence", None),
        ("robot/r1/mode/channel", None),
        ("robot/r1/sensor/lidar/rel/hb/0011223344556677", None),
        ("ceddp/presence", None),
    ],
)
def test_topic_names_follow_ros(rest: str, name: str | None) -> None:
    assert topic_name(F, f"arpz/{F}/{rest}") == name


def test_a_key_of_another_fleet_is_no_topic() -> None:
    assert topic_name(F, "arpz/other/robot/r1/sensor/lidar") is None


def stats(
    robot: str, stamp_s: float, *, sent: float, delivered: int, **extra: object
) -> RobotStats:
    return RobotStats(
        robot=robot,
        incarnation="abc",
        stamp_ns=int(stamp_s * 1e9),
        final=False,
        topics={"lidar": TopicCounters(sent=10, rate_hz=sent)},
        inbound={"cmd/velocity": InboundCounters(delivered=delivered)},
        **extra,  # type: ignore[arg-type]
    )


def channel_fleet() -> FleetObserver:
    """robot r1 (lidar at 10 Hz, a camera, velocity commands) in channel mode, with the CEDDP."""
    obs = FleetObserver(F)
    obs.on_token(keys.ceddp_presence_key(F), True)
    obs.on_token(keys.ceddp_mode_key(F, "channel"), True)
    obs.on_token(keys.presence_key(F, "r1"), True)
    obs.on_token(keys.robot_mode_key(F, "r1", "channel"), True)
    lidar = keys.sensor_key(F, "r1", "lidar")
    obs.on_token(wire.writer_token(lidar, "aa" * 8, encode_match_qos(SENSOR_QOS)), True)
    obs.on_token(wire.reader_token(lidar, "bb" * 8, encode_match_qos(SENSOR_QOS)), True)
    velocity = keys.command_key(F, "r1", "velocity")
    obs.on_token(wire.writer_token(velocity, "cc" * 8, encode_match_qos(COMMAND_QOS)), True)
    obs.on_token(wire.reader_token(velocity, "dd" * 8, encode_match_qos(COMMAND_QOS)), True)
    obs.on_token(
        wire.writer_token(keys.stats_key(F, "r1"), "ee" * 8, encode_match_qos(REPORT_QOS)), True
    )
    obs.on_report(
        keys.announce_key(F, "r1"),
        encode(
            Announce(
                robot="r1",
                incarnation="abc",
                sensors=[
                    TopicInfo(topic="lidar", kind="lidar", rate_hz=10.0, value_type="float"),
                    TopicInfo(topic="front", kind="camera", rate_hz=2.0, value_type="bytes"),
                ],
                commands=["velocity", "hello"],
            )
        ),
    )
    obs.on_report(keys.stats_key(F, "r1"), encode(stats("r1", 100.0, sent=9.5, delivered=10)))
    obs.on_report(keys.stats_key(F, "r1"), encode(stats("r1", 100.5, sent=9.5, delivered=20)))
    return obs


def test_the_graph_of_a_channel_fleet() -> None:
    graph = channel_fleet().graph()
    assert [(n.name, n.role, n.alive, n.mode) for n in graph.nodes] == [
        (CEDDP, "ceddp", True, "channel"),
        ("r1", "robot", True, "channel"),
    ]
    names = [t.name for t in graph.topics]
    assert names == sorted(names)
    assert set(names) == {
        "/r1/lidar",
        "/r1/front",
        "/r1/hello",
        "/r1/cmd/velocity",
        "/r1/cmd/hello",
        "/r1/stats",
        "/r1/announce",
        "/ceddp/stats",
    }
    lidar = graph.topic("/r1/lidar")
    assert lidar.ros_type == "sensor_msgs/msg/LaserScan"
    assert (lidar.arpz_type, lidar.value_type, lidar.kind) == ("Sample", "float", "lidar")
    assert (lidar.announced_rate_hz, lidar.measured_rate_hz) == (10.0, 9.5)
    assert [(w.node, w.guid) for w in lidar.writers] == [("r1", "aa" * 8)]
    assert [(r.node, r.guid) for r in lidar.readers] == [(CEDDP, "bb" * 8)]
    assert lidar.writers[0].describe_qos() == "RELIABLE VOLATILE"
    front = graph.topic("r1/front")
    assert front.key == keys.frames_key(F, "r1", "front")  # large kinds go as frames
    assert (front.arpz_type, front.ros_type, front.large) == (
        "LargeSample",
        "sensor_msgs/msg/Image",
        True,
    )
    velocity = graph.topic("/r1/cmd/velocity")
    assert (velocity.owner, velocity.arpz_type) == (CEDDP, "Command")
    # 10 commands delivered between two reports 0.5 s apart
    assert velocity.measured_rate_hz == pytest.approx(20.0)
    assert graph.topic("/r1/stats").measured_rate_hz == pytest.approx(2.0)
    assert graph.topic("/r1/cmd/hello").arpz_type == "Hello"


def test_a_topic_is_found_by_any_of_its_three_names() -> None:
    graph = channel_fleet().graph()
    lidar_key = keys.sensor_key(F, "r1", "lidar")
    for given in ("/r1/lidar", "r1/lidar", "r1/lidar/", lidar_key):
        assert graph.topic(given).key == lidar_key


def test_an_unknown_topic_names_the_closest() -> None:
    graph = channel_fleet().graph()
    with pytest.raises(UnknownTopicError, match=r"did you mean /r1/lidar"):
        graph.topic("/r1/lidr")
    with pytest.raises(UnknownTopicError, match=r"no topic 'nothing-like-it'"):
        graph.topic("nothing-like-it")


def test_an_empty_fleet_hints_at_the_other_fleets_on_the_router() -> None:
    obs = FleetObserver(F)
    obs.on_token("arpz/demo/ceddp/presence", True)
    with pytest.raises(UnknownTopicError, match=r"--fleet.*demo"):
        obs.graph().topic("/r1/lidar")


def test_tokens_that_vanish_leave_the_graph_and_own_readers_are_ignored() -> None:
    obs = channel_fleet()
    lidar = keys.sensor_key(F, "r1", "lidar")
    obs.on_token(wire.reader_token(lidar, "ff" * 8, encode_match_qos(SENSOR_QOS)), True)
    obs.ignore_guids.add("ff" * 8)
    assert [r.guid for r in obs.graph().topic("/r1/lidar").readers] == ["bb" * 8]
    obs.on_token(keys.presence_key(F, "r1"), False)
    obs.on_token(wire.reader_token(lidar, "bb" * 8, encode_match_qos(SENSOR_QOS)), False)
    graph = obs.graph()
    assert [n.alive for n in graph.nodes if n.name == "r1"] == [False]
    assert graph.topic("/r1/lidar").readers == ()


def test_a_plain_fleet_is_found_from_announcements_alone() -> None:
    obs = FleetObserver(F)
    obs.on_token(keys.presence_key(F, "r2"), True)
    obs.on_token(keys.robot_mode_key(F, "r2", "none"), True)
    obs.on_token(keys.ceddp_mode_key(F, "none"), True)
    announce = Announce(
        robot="r2",
        incarnation="x",
        sensors=[TopicInfo(topic="cam", kind="camera", rate_hz=1.0, value_type="bytes")],
        commands=["hello"],
        mode="none",
    )
    obs.on_report(keys.announce_key(F, "r2"), encode(announce))
    graph = obs.graph()
    cam = graph.topic("/r2/cam")
    assert cam.key == keys.sensor_key(F, "r2", "cam")  # one plain put per frame on sensor/
    assert cam.arpz_type == "LargeSample"
    assert not cam.reliable_channel
    assert [(w.node, w.plain, w.describe_qos()) for w in cam.writers] == [("r2", True, "plain")]
    assert graph.topic("/r2/cmd/hello").writers[0].node == CEDDP


def test_undecodable_reports_are_counted_not_raised() -> None:
    obs = FleetObserver(F)
    obs.on_report(keys.announce_key(F, "r1"), b"\xc1not msgpack")
    obs.on_report(keys.stats_key(F, "r1"), b"\x93\x01")
    assert obs.decode_errors == 2
    assert obs.graph().topics == ()


def test_repeated_stats_make_no_rate_and_order_does_not_matter() -> None:
    obs = FleetObserver(F)
    obs.on_report(keys.stats_key(F, "r1"), encode(stats("r1", 10.0, sent=1, delivered=0)))
    obs.on_report(keys.stats_key(F, "r1"), encode(stats("r1", 10.0, sent=1, delivered=0)))
    assert obs.stats_count("r1") == 1
    assert obs.graph().topic("/r1/stats").measured_rate_hz is None
    obs.on_report(keys.stats_key(F, "r1"), encode(stats("r1", 9.5, sent=1, delivered=0)))
    obs.on_report(keys.stats_key(F, "r1"), encode(stats("r1", 9.0, sent=1, delivered=0)))
    assert obs.stats_count("r1") == 2
    assert obs.graph().topic("/r1/stats").measured_rate_hz == pytest.approx(2.0)  # 9.5 -> 10


def test_matching_follows_the_qos_rules() -> None:
    obs = channel_fleet()
    lidar = keys.sensor_key(F, "r1", "lidar")
    # a BEST_EFFORT writer and a RELIABLE reader: incompatible (RELIABILITY)
    obs.on_token(wire.writer_token(lidar, "11" * 8, encode_match_qos(QOS_SENSOR_DATA)), True)
    # a reader asking for a deadline no writer offers: incompatible (DEADLINE)
    strict = QosProfile(deadline_s=0.05)
    obs.on_token(wire.reader_token(lidar, "22" * 8, encode_match_qos(strict)), True)
    pairs = matches(obs.graph().topic("/r1/lidar"))
    verdicts = {(m["writer"], m["reader"]): m["policy"] for m in pairs}
    assert verdicts == {
        ("aa" * 8, "bb" * 8): None,
        ("aa" * 8, "22" * 8): "DEADLINE",
        ("11" * 8, "bb" * 8): "RELIABILITY",
        ("11" * 8, "22" * 8): "RELIABILITY",
    }


def test_list_shows_every_topic_with_type_rate_qos_and_writer() -> None:
    text = "\n".join(list_lines(channel_fleet().graph()))
    assert "ceddp (channel), r1 (channel)" in text
    row = next(line for line in text.splitlines() if line.startswith("/r1/lidar "))
    for cell in ("sensor_msgs/msg/LaserScan", "Sample[float]", "9.5/10", "RELIABLE VOLATILE", "r1"):
        assert cell in row


def test_list_shows_a_failing_sensor() -> None:
    """Issue 41: a robot whose driver raised on every read showed "0.0/5" and nothing else."""
    obs = channel_fleet()
    failing = RobotStats(
        robot="r1",
        incarnation="abc",
        stamp_ns=int(101e9),
        final=False,
        topics={
            "lidar": TopicCounters(produced=40, driver_errors=40, driver_exceptions=40),
            "front": TopicCounters(produced=4, sent=4, late_reads=2),
        },
        silent_sensors=["lidar"],
    )
    obs.on_report(keys.stats_key(F, "r1"), encode(failing))
    rows = {line.split()[0]: line for line in list_lines(obs.graph()) if line.startswith("/r1/")}
    assert "NO READING, 40 driver errors" in rows["/r1/lidar"]
    assert "2 late reads" in rows["/r1/front"]
    assert " - " in rows["/r1/stats"]


def test_the_clock_offset_comes_from_the_robots_stats() -> None:
    assert clock_offset(None) is None
    no_clock = stats("r1", 1.0, sent=1, delivered=0)
    assert clock_offset(no_clock) is None
    assert clock_offset(stats("r1", 1.0, sent=1, delivered=0, clock=ClockStats())) is None
    measured = stats(
        "r1", 1.0, sent=1, delivered=0, clock=ClockStats(offset_ns=-2_000_000, delay_ns=300_000)
    )
    offset = clock_offset(measured)
    assert offset is not None and (offset.offset_ns, offset.delay_ns) == (-2_000_000, 300_000)


def test_a_name_two_topics_share_asks_for_the_key() -> None:
    obs = channel_fleet()
    announce = Announce(
        robot="r1",
        incarnation="abc",
        sensors=[TopicInfo(topic="stats", kind="imu", rate_hz=1.0, value_type="float")],
        commands=[],
    )
    obs.on_report(keys.announce_key(F, "r1"), encode(announce))
    graph = obs.graph()
    with pytest.raises(UnknownTopicError, match=r"names 2 topics .*give the arpz key"):
        graph.topic("/r1/stats")
    assert graph.topic(keys.sensor_key(F, "r1", "stats")).kind == "imu"
    assert graph.topic(keys.stats_key(F, "r1")).arpz_type == "RobotStats"


def test_discovery_over_a_transport_finds_the_reports_and_hides_its_own_readers() -> None:
    """Through the channel (TRANSIENT_LOCAL: reports written before discovery started arrive at
    once) and with the robot's presence token; discovery's own readers are not in the graph."""
    bus = MemoryBus()
    with (
        closing(MemoryTransport(bus)) as robot,
        closing(MemoryTransport(bus)) as tool,
        Writer(robot, keys.announce_key(F, "r1"), REPORT_QOS) as announce_out,
        Writer(robot, keys.stats_key(F, "r1"), REPORT_QOS) as stats_out,
    ):
        robot.declare_token(keys.presence_key(F, "r1"))
        announce = Announce(
            robot="r1",
            incarnation="abc",
            sensors=[TopicInfo(topic="lidar", kind="lidar", rate_hz=5.0, value_type="float")],
            commands=[],
        )
        announce_out.write(encode(announce))
        stats_out.write(encode(stats("r1", 1.0, sent=5.0, delivered=0)))
        stats_out.write(encode(stats("r1", 1.5, sent=5.0, delivered=0)))
        with discovering(tool, F) as discovery:
            graph = discovery.settle(max_s=5.0)
        lidar = graph.topic("/r1/lidar")
        assert (lidar.ros_type, lidar.measured_rate_hz) == ("sensor_msgs/msg/LaserScan", 5.0)
        assert [n.name for n in graph.nodes] == ["r1"]
        assert graph.topic("/r1/stats").readers == ()  # discovery's own reader is hidden
        assert [w.guid for w in graph.topic("/r1/stats").writers] == [stats_out.guid]


def test_discovery_learns_from_the_ceddp_that_access_control_is_in_force() -> None:
    """The CEDDP's stats say whether access control is in force: then a tool holds an
    observer's rights at most, and the graph says it must read without writing. Discovery
    waits for them when the CEDDP is present."""
    bus = MemoryBus()
    with (
        closing(MemoryTransport(bus)) as ceddp,
        closing(MemoryTransport(bus)) as tool,
        Writer(ceddp, keys.ceddp_stats_key(F), REPORT_QOS) as stats_out,
    ):
        ceddp.declare_token(f"{keys.fleet_prefix(F)}/ceddp/presence")
        with discovering(tool, F) as discovery:
            assert discovery.settle(max_s=0.5).read_only is False  # no stats yet: unknown
            stats_out.write(
                encode(CeddpStats(stamp_ns=1, cpu_percent=0.0, topics=[], access_control=True))
            )
            graph = discovery.settle(max_s=5.0)
        assert graph.read_only and graph.ceddp_stats is not None
        assert [(n.name, n.alive) for n in graph.nodes] == [("ceddp", True)]


def test_discovery_watches_its_own_fleet_apart_from_the_others() -> None:
    """A subscription to all of arpz/** is refused whole where access control allows only the
    fleet's keys (an observer): the fleet's tokens come from a watch of arpz/{fleet}/**, and
    the other fleets' names from the one of arpz/**."""
    bus = MemoryBus()
    with closing(MemoryTransport(bus)) as robot, closing(MemoryTransport(bus)) as tool:
        robot.declare_token(keys.presence_key(F, "r1"))
        robot.declare_token(keys.presence_key("other", "r9"))
        watched: list[str] = []
        real_watch = tool.watch_liveliness

        def watch(expr: str, callback: Any) -> Any:
            watched.append(expr)
            return real_watch(expr, callback)

        tool.watch_liveliness = watch  # type: ignore[method-assign]
        with discovering(tool, F) as discovery:
            graph = discovery.settle(max_s=0.5)
        assert f"{keys.fleet_prefix(F)}/**" in watched and f"{keys.ROOT}/**" in watched
        assert [(n.name, n.alive) for n in graph.nodes] == [("r1", True)]
        assert graph.other_fleets == ("other",)
