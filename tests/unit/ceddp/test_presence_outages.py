"""A robot that goes away and comes back as the same incarnation is one outage with its
duration, not a new robot (issue 39); one that comes back restarted is told apart."""

from __future__ import annotations

import msgspec

from arpz.ceddp.server import CeddpServer
from arpz.core import keys
from arpz.core.config import CeddpConfig
from arpz.core.messages import RobotStats
from arpz.transport.memory import MemoryBus, MemoryTransport


def _stats(incarnation: str) -> bytes:
    stats = RobotStats(robot="r1", incarnation=incarnation, stamp_ns=1, final=False, topics={})
    return msgspec.msgpack.encode(stats)


def _server() -> CeddpServer:
    return CeddpServer(CeddpConfig(fleet="f", rrd="unused.rrd"), MemoryTransport(MemoryBus()))


def _away_and_back(incarnation_after: str) -> CeddpServer:
    """r1 joins as incarnation aaaa, its presence vanishes and comes back, and its first report
    after names ``incarnation_after``."""
    server = _server()
    control = server.control
    presence, stats = keys.presence_key("f", "r1"), keys.stats_key("f", "r1")
    control._handle_presence(presence, True)
    control._handle_report(stats, _stats("aaaa"))
    control._handle_presence(presence, False)
    control._handle_presence(presence, True)
    control._handle_report(stats, _stats(incarnation_after))
    return server


def test_a_robot_back_as_the_same_incarnation_is_one_outage_with_its_duration() -> None:
    server = _away_and_back("aaaa")
    record = server.control.robots["r1"]
    assert len(record.outages) == 1 and 0 <= record.outages[0] < 1.0
    events = [e.split(": ", 1)[1] for e in server.events]
    assert events[0] == "robot r1 joined"
    assert events[1].startswith("robot r1 unreachable")
    assert "back after" in events[2] and "same incarnation" in events[2]
    assert len(events) == 3
    assert server.summary()["robots"]["r1"]["outages_s"] == [round(record.outages[0], 3)]


def test_a_robot_back_as_a_new_incarnation_is_a_restart_not_an_outage() -> None:
    server = _away_and_back("bbbb")
    assert server.control.robots["r1"].outages == []
    events = [e.split(": ", 1)[1] for e in server.events]
    assert "new incarnation bbbb" in events[-1]
