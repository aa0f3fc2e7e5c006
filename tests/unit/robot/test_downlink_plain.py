"""The robot's downlink in plain mode (``reliability = "none"``): commands are plain Zenoh puts,
and a gap in their seq is counted as lost, as the CEDDP counts plain sensor samples."""

import threading

from arpz.core.config import RobotConfig
from arpz.core.messages import Command, encode
from arpz.robot.actuation import RecordingActuator
from arpz.robot.agent import RobotAgent
from arpz.transport.memory import MemoryBus, MemoryTransport
from tests.support import wait_until


def test_plain_commands_count_seq_gaps_as_lost() -> None:
    bus = MemoryBus()
    actuator = RecordingActuator(commands=["velocity"])
    agent = RobotAgent(
        RobotConfig(robot_id="r1", fleet="f", reliability="none", match_timeout_s=0.1),
        MemoryTransport(bus),
        actuator=actuator,
    )
    ceddp = MemoryTransport(bus)
    stop = threading.Event()
    agent.start()
    thread = threading.Thread(target=agent.run, args=(stop,))
    thread.start()
    try:
        for seq in (1, 2, 5, 6):  # 3 and 4 never sent: lost on the way
            ceddp.put("arpz/f/robot/r1/cmd/velocity", encode(Command("ceddp:a", seq, 1, 0.5)))
        wait_until(lambda: actuator.counts["velocity"] == 4, what="four commands applied")
        # a new CEDDP incarnation starts its own count: not a gap
        ceddp.put("arpz/f/robot/r1/cmd/velocity", encode(Command("ceddp:b", 1, 1, 0.5)))
        wait_until(lambda: actuator.counts["velocity"] == 5, what="the new writer's command")
        inbound = agent.inbound()["cmd/velocity"]
        assert inbound.lost == 2 and inbound.refused == 0, inbound
    finally:
        stop.set()
        thread.join(5)
        agent.shutdown()


def test_a_channel_robot_refuses_plain_commands_and_says_so() -> None:
    bus = MemoryBus()
    actuator = RecordingActuator(commands=["velocity"])
    agent = RobotAgent(
        RobotConfig(robot_id="r1", fleet="f", match_timeout_s=0.1),
        MemoryTransport(bus),
        actuator=actuator,
    )
    ceddp = MemoryTransport(bus)
    agent.start()
    try:
        for seq in (1, 2, 3):
            ceddp.put("arpz/f/robot/r1/cmd/velocity", encode(Command("ceddp:a", seq, 1, 0.5)))
        wait_until(
            lambda: agent.inbound()["cmd/velocity"].refused == 3, what="three refused commands"
        )
        assert actuator.counts["velocity"] == 0
        # the event comes from the reader's control thread, after the refusal itself
        wait_until(
            lambda: any(
                "cmd/velocity" in line for line in agent.stats(final=False).incompatible_qos
            ),
            what="the INCOMPATIBLE_QOS event in the robot's report",
        )
    finally:
        agent.shutdown()
