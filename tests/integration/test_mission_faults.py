"""Issue 39 through the real router: the two-robot hallway mission (robot1 leads, robot2
follows) with robot1 cut off in the first corner, by a dead link (an ``arpz.netem`` outage on
its ``udp/`` link) or a frozen process (SIGSTOP: a TCP session that hears nothing), as real
CEDDP and robot processes. Before the fix robot2 drove into a wall on a later leg: the planner
held the fleet for robot1's stale data 0.3 s after its last reading, but robot1 had turned more
(it drove on its last command to its 0.5 s watchdog) or less (frozen) than robot2 by then, and
robot2, steered with robot1's velocity alone, kept the heading error. The mission must end
without a collision: robot2 is steered back into its lane from its own side beams."""

from __future__ import annotations

import json
import os
import re
import signal
from importlib import resources
from pathlib import Path
from typing import Literal

import pytest

from arpz.netem import Impairments, Outage
from tests.integration.fleet import Process, ceddp, settle, udp_link
from tests.support import wait_until

# three processes on a 20 Hz control loop judged by a 0.3 s staleness rule: with the cores to
# itself (tests/conftest.py, cpu_share), as the other mission tests
pytestmark = [pytest.mark.integration, pytest.mark.slow, pytest.mark.cpu_exclusive]

#: the mission's time limit: hallway_small takes about 33 s, plus the outage and the holds
TIME_LIMIT_S = 75.0


def two_robot_world(tmp: Path) -> Path:
    """hallway_small with robot1 and robot2 only (robot2 1 m diagonally behind, inner lane)."""
    text = resources.files("arpz.mission").joinpath("maps/hallway_small.toml").read_text("utf-8")
    path = tmp / "two_robots.toml"
    path.write_text(text[: text.index("[robots.robot3]")].replace("hallway_small", "two_robots"))
    return path


def sim_robot(tmp: Path, robot: str, endpoint: str, world: Path) -> Process:
    config = tmp / f"{robot}.toml"
    config.write_text(
        f'robot_id = "{robot}"\nfleet = "itest"\nconnect = ["{endpoint}"]\n'
        f'seed = {robot[-1]}\n[sim]\nworld = "{world.as_posix()}"\n'
    )
    return Process(robot, ["-m", "arpz.robot", "--config", str(config)], tmp)


@pytest.mark.parametrize(("cut", "duration_s"), [("link", 3.0), ("frozen", 12.0)])
def test_robot1_cut_off_in_a_corner_ends_the_mission_without_a_collision(
    tmp_path: Path, cut: Literal["link", "frozen"], duration_s: float
) -> None:
    world = two_robot_world(tmp_path)
    link = udp_link()
    # the fixture's CEDDP writes summary.json, with the mission's verdict, when it stops
    mission = f'[mission]\nworld = "{world.as_posix()}"\ntime_limit_s = {TIME_LIMIT_S}\n'
    with ceddp(tmp_path, extra=mission, also_listen=(link.ceddp_endpoint,)) as (server, tcp):
        link.proxy.start()
        robot1 = sim_robot(tmp_path, "robot1", link.robot_endpoint if cut == "link" else tcp, world)
        robot2 = sim_robot(tmp_path, "robot2", tcp, world)
        frozen = False
        try:
            robot1.wait_for("running")
            robot2.wait_for("running")
            wait_until(
                lambda: "mission turn_started: corner 1:" in server.output(),
                timeout_s=40,
                what="the fleet's first corner",
                interval_s=0.01,
            )
            settle(0.3)  # deliberately: the cut lands in the middle of the turn
            if cut == "link":
                link.impair(Impairments(outages=(Outage(start_s=0.0, duration_s=duration_s),)))
                settle(duration_s)  # the dead zone itself
            else:
                os.kill(robot1.popen.pid, signal.SIGSTOP)
                frozen = True
                settle(duration_s)  # deliberately: the freeze itself
                os.kill(robot1.popen.pid, signal.SIGCONT)
                frozen = False
            wait_until(
                lambda: "arpz.ceddp: mission " in server.output(),
                timeout_s=TIME_LIMIT_S + 15,
                what="the mission's verdict",
                interval_s=0.2,
            )
            verdict = next(line for line in server.lines if line.startswith("arpz.ceddp: mission "))
            for robot in (robot1, robot2):
                assert robot.interrupt(timeout_s=30) == 0, robot.output()
        finally:
            if frozen:
                os.kill(robot1.popen.pid, signal.SIGCONT)
            robot1.kill()
            robot2.kill()
            link.proxy.stop()
        assert server.interrupt() == 0, server.output()
    log = server.output()
    result = json.loads((tmp_path / "summary.json").read_text())["mission"]["result"]
    # the planner held the whole fleet for robot1's stale data, then moved it again
    assert re.search(r"mission stale_stop: robot1 lidar_\d+: 0\.\d\d s old", log), log
    # (its readings back first, the fleet may wait for its commands to be acknowledged too)
    assert re.search(r"mission resumed: (data fresh|commands acknowledged) again", log), log
    # ... and however the mission ended, nobody touched anything
    assert result["failure"] != "collision", verdict
    assert "collision" not in verdict, verdict
