"""Robot agents and the CEDDP over the in-memory transport: fast checks of the wiring.

The same flows go through a real router and real processes in tests/integration/test_fleet.py.
"""

import threading

from arpz.ceddp.server import CeddpServer
from arpz.core.config import CeddpConfig, HelloConfig, RobotConfig
from arpz.robot.agent import RobotAgent
from arpz.transport.memory import MemoryBus, MemoryTransport
from tests.support import wait_until


def test_counts_reconcile_and_hello_round_trips() -> None:
    bus = MemoryBus()
    server = CeddpServer(
        CeddpConfig(fleet="f", rrd="unused.rrd", metrics_period_s=0.05), MemoryTransport(bus)
    )
    server.start()
    agents = [
        RobotAgent(
            RobotConfig(
                robot_id="r1",
                fleet="f",
                preset="machine1",
                preset_rate_hz=200,
                hello=HelloConfig(enabled=True, rate_hz=50),
                stats_period_s=0.1,
            ),
            MemoryTransport(bus),
        ),
        RobotAgent(
            RobotConfig(robot_id="r2", fleet="f", preset="machine2", preset_rate_hz=200),
            MemoryTransport(bus),
        ),
    ]
    stop = threading.Event()
    threads = [threading.Thread(target=a.run, args=(stop,)) for a in agents]
    for agent in agents:
        agent.start()
    for t in threads:
        t.start()
    wait_until(lambda: agents[0].hello.received >= 10, what="10 Hello round trips")

    def every_robot_held_back_and_reported() -> bool:
        return all(
            sum(c.held_back for c in agent.counters().values()) > 0
            and (record := server.robots.get(agent.config.robot_id)) is not None
            and record.stats is not None
            for agent in agents
        )

    wait_until(
        every_robot_held_back_and_reported,
        what="each robot to hold a reading back and the CEDDP to hold a stats report of each",
    )
    stop.set()
    for t in threads:
        t.join(5)
    for agent in agents:
        agent.shutdown()
    summary = server.shutdown()
    for agent in agents:
        row = summary["robots"][agent.config.robot_id]
        counters = agent.counters()
        assert row["final_stats"]
        assert row["produced"] == sum(c.produced for c in counters.values()) > 0
        assert row["produced"] == row["sent"] + row["held_back"]
        assert row["received"] == row["sent"] and row["lost"] == 0
        assert row["held_back"] > 0
        for topic, t in row["topics"].items():
            if topic != "hello":
                assert t["cc_discarded"] + t["cc_passed"] == t["received"]
    hello = summary["robots"]["r1"]["hello"]
    assert hello["sent"] == hello["received"] + hello["lost"]
    # presence and samples are handled by different workers: a Hello processed before the
    # robot's presence cannot be relayed, and is counted as such
    assert hello["lost"] == summary["hello_relay"]["no_relay"]


def test_qos_is_assigned_whether_the_announcement_or_the_presence_comes_first() -> None:
    from arpz.core.config import QosControlConfig
    from arpz.core.messages import QOS_ASSIGNMENT_DECODER, Announce, TopicInfo, encode

    bus = MemoryBus()
    server = CeddpServer(
        CeddpConfig(fleet="f", rrd="unused.rrd", qos=QosControlConfig(enabled=True)),
        MemoryTransport(bus),
    )
    server.start()
    robot = MemoryTransport(bus)
    seen: list[set[str]] = []
    robot.subscribe(
        "arpz/f/ceddp/qos",
        lambda k, p, a: seen.append(set(QOS_ASSIGNMENT_DECODER.decode(p).robots)),
    )
    announce = Announce(
        robot="r1",
        incarnation="i",
        commands=["hello"],
        sensors=[TopicInfo(topic="pir", kind="pir", rate_hz=10, value_type="str")],
    )
    # through the channel, as a robot reports (a plain put would be refused as INCOMPATIBLE)
    from arpz.channel import Writer
    from arpz.core.traffic import REPORT_QOS

    writer = Writer(robot, "arpz/f/robot/r1/announce", REPORT_QOS)
    writer.write(encode(announce))  # before its presence

    def announcement_handled() -> bool:
        record = server.robots.get("r1")
        return record is not None and record.announce is not None

    wait_until(announcement_handled, what="the CEDDP to handle r1's announcement")
    assert not server.robots["r1"].alive  # the announcement did come first
    robot.declare_token("arpz/f/robot/r1/presence")
    wait_until(lambda: {"r1"} in seen, what="an assignment for r1")
    writer.close()
    server.shutdown()
