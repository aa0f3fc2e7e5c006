"""The CEDDP follows one incarnation per robot (issue 41): a restart starts the live counters
from zero with only the robot's current topics, its earlier incarnations summed apart; two
processes running with one robot_id are found when the one superseded reports again, the newer
one's samples dropped and counted, loudly; a failing sensor shows though nothing arrived from it.
Real processes through a real router: tests/integration/test_sensor_health.py."""

from __future__ import annotations

from prometheus_client import generate_latest

from arpz.ceddp.dashboard import HEALTH_METRICS
from arpz.ceddp.server import CeddpServer
from arpz.ceddp.web import registry_for
from arpz.core import keys
from arpz.core.config import CeddpConfig
from arpz.core.messages import (
    Announce,
    RobotStats,
    Sample,
    TopicCounters,
    TopicInfo,
    encode,
    writer_id,
)
from arpz.transport.memory import MemoryBus, MemoryTransport

FLEET = "f"


def _server() -> CeddpServer:
    return CeddpServer(CeddpConfig(fleet=FLEET, rrd="unused.rrd"), MemoryTransport(MemoryBus()))


class _Robot:
    """One incarnation of r1 as the CEDDP hears it: reports and samples."""

    def __init__(self, server: CeddpServer, incarnation: str, started_ns: int) -> None:
        self.server, self.incarnation, self.started_ns = server, incarnation, started_ns
        self.seqs: dict[str, int] = {}
        self.stamp = 0

    def announce(self, *topics: str) -> None:
        sensors = [TopicInfo(t, "lidar", 10.0, "float") for t in topics]
        payload = encode(Announce("r1", self.incarnation, sensors, ["hello"]))
        self.server.control._handle_report(keys.announce_key(FLEET, "r1"), payload)

    def samples(self, topic: str, count: int) -> None:
        key = keys.sensor_key(FLEET, "r1", topic)
        for _ in range(count):
            seq = self.seqs[topic] = self.seqs.get(topic, 0) + 1
            sample = Sample(writer_id("r1", self.incarnation), seq, 1_000, float(seq))
            self.server.ingest.handle_sensor(key, encode(sample), 2_000)

    def stats(self, final: bool = False, **extra: TopicCounters) -> None:
        self.stamp += 1
        topics = {t: TopicCounters(produced=n, sent=n, last_seq=n) for t, n in self.seqs.items()}
        stats = RobotStats(
            robot="r1",
            incarnation=self.incarnation,
            stamp_ns=self.stamp,
            final=final,
            topics={**topics, **extra},
            started_ns=self.started_ns,
        )
        self.server.control._handle_report(keys.stats_key(FLEET, "r1"), encode(stats))


def _metrics(server: CeddpServer) -> str:
    return generate_latest(registry_for(server.status.read)).decode()


def test_a_restart_starts_the_live_counters_afresh_with_only_its_topics() -> None:
    server = _server()
    first = _Robot(server, "aaaa", started_ns=1)
    first.announce("a", "b")
    first.samples("a", 7)
    first.samples("b", 5)
    first.stats()
    first.stats(final=True)
    second = _Robot(server, "bbbb", started_ns=2)
    second.announce("c")
    second.samples("c", 3)
    second.stats()
    robot = server.status.read().robots[0]
    assert robot.incarnation == "bbbb"
    assert [t.topic for t in robot.topics] == ["c"]
    assert (robot.received, robot.sent) == (3, 3)
    assert robot.previous.incarnations == 1
    assert (robot.previous.received, robot.previous.sent) == (12, 12)
    text = _metrics(server)
    assert 'arpz_robot_samples_sent_total{robot="r1",topic="c"} 3.0' in text
    assert 'topic="a"' not in text and 'topic="b"' not in text
    assert 'arpz_robot_previous_samples_received_total{robot="r1"} 12.0' in text
    assert 'arpz_robot_incarnation_info{incarnation="bbbb",robot="r1"} 1.0' in text
    # the summary keeps the whole run, per incarnation
    row = server.summary()["robots"]["r1"]
    assert row["incarnation"] == "bbbb" and set(row["incarnations"]) == {"aaaa", "bbbb"}
    assert row["incarnations"]["aaaa"]["reconciled"] is True


def test_a_second_process_with_the_robot_id_is_flagged_and_its_samples_dropped() -> None:
    server = _server()
    first = _Robot(server, "aaaa", started_ns=100)
    first.announce("lidar")
    first.samples("lidar", 10)
    first.stats()
    # a second process: the CEDDP takes it for a restart at first...
    second = _Robot(server, "bbbb", started_ns=200)
    second.announce("lidar")
    second.samples("lidar", 4)
    second.stats()
    assert server.control.robots["r1"].incarnation == "bbbb"
    # ...until the first reports again: both run, the first started first and is followed
    first.samples("lidar", 2)
    first.stats()
    record = server.control.robots["r1"]
    assert record.incarnation == "aaaa" and set(record.duplicates) == {"bbbb"}
    errors = [e for e in server.events if "two processes run as r1" in e]
    assert len(errors) == 1 and "bbbb's samples are dropped" in errors[0], server.events
    second.samples("lidar", 6)  # dropped, counted
    first.samples("lidar", 3)
    second.stats()  # ignored: not the robot's report
    first.stats()
    assert server.control.robots["r1"].stats.incarnation == "aaaa"  # type: ignore[union-attr]
    robot = server.status.read().robots[0]
    assert (robot.incarnation, robot.duplicates, robot.duplicate_dropped) == ("aaaa", ["bbbb"], 6)
    assert robot.received == 15  # the first's own samples only
    server.metrics.tick()
    assert server.metrics.last_frame.robots["r1"]["duplicate_processes"] == 1.0  # type: ignore[union-attr]
    assert 'arpz_robot_duplicate_processes{robot="r1"} 1.0' in _metrics(server)
    row = server.summary()["robots"]["r1"]
    assert row["duplicates"]["bbbb"]["running"] is True
    assert row["topics"]["lidar"]["duplicate_dropped"] == 6
    # once the first stops, the other one is the robot: its samples count again
    first.stats(final=True)
    second.stats()
    record = server.control.robots["r1"]
    assert record.incarnation == "bbbb" and not record.duplicates
    second.samples("lidar", 2)
    assert server.status.read().robots[0].received == 6  # 4 before, 2 now (6 dropped: a gap)


def test_a_repeated_or_final_report_of_an_earlier_incarnation_is_no_duplicate() -> None:
    server = _server()
    first = _Robot(server, "aaaa", started_ns=1)
    first.stats()
    second = _Robot(server, "bbbb", started_ns=2)
    second.stats()
    control = server.control
    again = RobotStats(robot="r1", incarnation="aaaa", stamp_ns=1, final=False, topics={})
    control._handle_report(keys.stats_key(FLEET, "r1"), encode(again))  # a resent report
    first.stats(final=True)  # its last words
    record = control.robots["r1"]
    assert record.incarnation == "bbbb" and not record.duplicates
    assert not [e for e in server.events if "two processes" in e]


def test_a_sensor_whose_driver_fails_shows_though_nothing_arrived() -> None:
    server = _server()
    robot = _Robot(server, "aaaa", started_ns=1)
    robot.samples("ok", 4)
    failing = TopicCounters(
        produced=9, driver_errors=9, driver_exceptions=9, last_driver_error="OSError: gone"
    )
    robot.stats(temp=failing)
    stats = server.control.robots["r1"].stats
    assert stats is not None
    server.control.robots["r1"].stats = RobotStats(
        **{**{f: getattr(stats, f) for f in stats.__struct_fields__}, "silent_sensors": ["temp"]}
    )
    status = server.status.read().robots[0]
    temp = {t.topic: t for t in status.topics}["temp"]
    assert (temp.received, temp.driver_errors, temp.silent) == (0, 9, True)
    assert temp.last_driver_error == "OSError: gone"
    assert (status.driver_errors, status.silent_sensors) == (9, ["temp"])
    text = _metrics(server)
    assert 'arpz_robot_driver_errors_total{robot="r1",topic="temp"} 9.0' in text
    assert 'arpz_robot_sensor_silent{robot="r1",topic="temp"} 1.0' in text
    row = server.summary()["robots"]["r1"]
    assert row["driver_errors"] == 9 and row["silent_sensors"] == ["temp"]
    topic = row["topics"]["temp"]
    assert topic["produced"] == topic["sent"] + topic["held_back"] + topic["driver_errors"]
    assert topic["lost"] == 0 and topic["silent"]
    server.metrics.tick()
    frame = server.metrics.last_frame
    assert frame is not None and frame.robots["r1"]["driver_errors"] == 9.0
    # every health series the dashboard's blueprint has a view for is in the frame
    assert set(HEALTH_METRICS) <= set(frame.robots["r1"])
