"""A robot agent with a simulated body, over the in-memory transport."""

import threading
import time

from arpz.core.config import RobotConfig, SimConfig
from arpz.core.messages import SAMPLE_DECODER, TELEMETRY_DECODER, Command, encode
from arpz.robot.agent import RobotAgent
from arpz.transport.memory import MemoryBus, MemoryTransport
from tests.support import wait_until


def test_velocity_commands_drive_the_body_and_beams_are_published() -> None:
    bus = MemoryBus()
    agent = RobotAgent(
        RobotConfig(
            robot_id="robot1",
            fleet="f",
            sim=SimConfig(world="hallway_small", noise_std_m=0.0),
            # plain Zenoh on both sides: this test is about the body, not the channel
            reliability="none",
            match_timeout_s=0.2,
        ),
        MemoryTransport(bus),
    )
    server = MemoryTransport(bus)
    beams: dict[str, float] = {}
    poses: list[tuple[float, float]] = []
    server.subscribe(
        "arpz/f/robot/robot1/sensor/*",
        lambda k, p, a: beams.__setitem__(k.rsplit("/", 1)[-1], SAMPLE_DECODER.decode(p).value),
    )
    server.subscribe(
        "arpz/f/robot/robot1/telemetry",
        lambda k, p, a: poses.append(
            (TELEMETRY_DECODER.decode(p).x_m, TELEMETRY_DECODER.decode(p).y_m)
        ),
    )
    stop = threading.Event()
    thread = threading.Thread(target=agent.run, args=(stop,))
    agent.start()
    thread.start()
    try:
        wait_until(lambda: len(beams) == 8 and bool(poses), what="8 beams and a pose")
        # home (6.0, 1.5) heading west in hallway_small: 1.5 m from the south wall at 270 deg
        assert abs(beams["lidar_270"] - 1.5) < 0.02
        assert abs(beams["lidar_90"] - 1.5) < 0.02  # the central block starts at y = 3
        x0 = poses[-1][0]
        for seq in range(1, 30):  # 0.5 m/s west for ~0.6 s, refreshed before the watchdog
            server.put(
                "arpz/f/robot/robot1/cmd/velocity",
                encode(Command("ceddp:x", seq, time.time_ns(), [0.5, 0.0])),
            )
            time.sleep(0.02)
        wait_until(lambda: poses[-1][0] < x0 - 0.15, what="the body moved west")
        assert abs(poses[-1][1] - 1.5) < 0.01
    finally:
        stop.set()
        thread.join(5)
        agent.shutdown()
