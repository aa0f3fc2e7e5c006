"""The closed loop without a network: three bodies, the hallway planner and the judge in one loop.

The network is reduced to what matters to the mission: how often each robot's beams reach the
planner (``beam_rate_hz``), how late (``latency_s``), optionally which readings arrive wrong
or not at all (``corrupt``), when a robot's link is down or its process frozen
(``outages``), and when the planner learns that a robot got its commands (``ack_period_s``:
the reliable channel's acknowledgements). Time is simulated, so a 100 s mission runs in about
a second and the same arguments give the same run.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import msgspec
import numpy as np

from arpz.mission.body import RobotBody
from arpz.mission.hallway import HallwayPlanner, PlannerSettings
from arpz.mission.judge import Judge, JudgeSettings, MissionResult
from arpz.mission.lidar import Lidar
from arpz.mission.vocabulary import MissionEvent, VelocityCommand
from arpz.mission.world import FloatArray, World

#: ``corrupt(robot, beam_deg, t_s, range_m)`` returns the value the planner receives instead, or
#: None to lose the reading: a way to inject a phantom obstacle or a dead beam.
Corruption = Callable[[str, int, float, float], float | None]


@dataclass(frozen=True)
class Outage:
    """One robot cut off from the CEDDP from ``start_s`` for ``duration_s`` (simulated seconds).

    ``kind="link"``: its link is down both ways (a dead zone, a roam): what it measures and what
    is sent to it are lost, and its body drives on its last command until its command timeout,
    as a real robot's watchdog lets it; ``"uplink"`` or ``"downlink"``: one way only (its
    readings, or the commands to it). ``kind="frozen"``: its process is stopped (SIGSTOP): it
    measures, sends and moves nothing, and its last command has expired when it wakes up.
    """

    robot: str
    start_s: float
    duration_s: float
    kind: Literal["link", "uplink", "downlink", "frozen"] = "link"

    def __post_init__(self) -> None:
        if not (self.start_s >= 0.0 and self.duration_s > 0.0):
            raise ValueError(
                f"Outage of {self.robot}: start_s must be >= 0 and duration_s > 0, "
                f"got {self.start_s} and {self.duration_s}"
            )

    def covers(self, robot: str, t_s: float) -> bool:
        return robot == self.robot and self.start_s <= t_s < self.start_s + self.duration_s


@dataclass(frozen=True)
class OfflineRun:
    result: MissionResult
    #: Per robot, rows of (t_s, x_m, y_m, theta_rad): the true path.
    paths: dict[str, FloatArray]
    events: list[MissionEvent]
    beams_delivered: int


def run_offline(
    world: World,
    planner_settings: PlannerSettings,
    beam_rate_hz: float,
    duration_s: float,
    *,
    judge_settings: JudgeSettings | None = None,
    tick_hz: float = 20.0,
    step_s: float = 0.02,
    latency_s: float = 0.0,
    noise_std_m: float = 0.0,
    seed: int = 0,
    corrupt: Corruption | None = None,
    outages: Sequence[Outage] = (),
    ack_period_s: float = 0.05,
) -> OfflineRun:
    """Run the hallway mission for at most ``duration_s`` simulated seconds (the time limit).

    Each robot scans all its beams every ``1 / beam_rate_hz`` seconds from a random phase (the
    robots' clocks are not aligned); readings reach the planner ``latency_s`` later, stamped with
    their measurement time, and commands reach the bodies ``latency_s`` after each planner tick.
    A reading or command that would arrive while its robot is in an ``Outage`` is lost.

    Every ``ack_period_s`` from a random phase each robot acknowledges every command that
    reached it, if the request can reach it and its acknowledgement can come back (its
    downlink and uplink up, its process running); the planner learns it ``latency_s`` later
    (``HallwayPlanner.on_command_ack``), as the CEDDP learns it from the channel's
    acknowledgements (``arpz.ceddp.downlink``). In the lab a robot's commands were
    acknowledged within one 50 ms tick, on clean and on 15 % lossy QUIC links.
    """
    if (
        beam_rate_hz <= 0.0
        or tick_hz <= 0.0
        or step_s <= 0.0
        or duration_s <= 0.0
        or ack_period_s <= 0.0
    ):
        raise ValueError(
            "beam_rate_hz, tick_hz, step_s, duration_s and ack_period_s must all be > 0"
        )
    for outage in outages:
        if outage.robot not in planner_settings.robots:
            raise ValueError(f"Outage of {outage.robot!r}, which is not in the fleet")

    def cut_off(robot: str, t_s: float, kinds: tuple[str, ...]) -> bool:
        return any(o.kind in kinds and o.covers(robot, t_s) for o in outages)

    readings_lost = ("link", "uplink", "frozen")
    commands_lost = ("link", "downlink", "frozen")

    judge_settings = msgspec.structs.replace(
        judge_settings if judge_settings is not None else JudgeSettings(),
        time_limit_s=duration_s,
        obstacle_range_m=planner_settings.obstacle_range_m,
        max_range_m=planner_settings.max_range_m,
    )
    rng = np.random.default_rng(seed)
    robots = planner_settings.robots
    bodies = {
        robot: RobotBody(
            world,
            robot,
            lidar=Lidar(
                world,
                max_range_m=planner_settings.max_range_m,
                noise_std_m=noise_std_m,
                seed=seed * 101 + index,
            ),
        )
        for index, robot in enumerate(robots)
    }
    planner = HallwayPlanner(planner_settings)
    judge = Judge(world, judge_settings)

    beam_period_s = 1.0 / beam_rate_hz
    tick_period_s = 1.0 / tick_hz
    next_scan_s = {robot: float(rng.uniform(0.0, beam_period_s)) for robot in robots}
    next_tick_s = 0.0
    beams_in_flight: deque[tuple[float, str, int, float, float]] = deque()
    commands_in_flight: deque[tuple[float, dict[str, VelocityCommand]]] = deque()
    # per robot, when each command not yet known acknowledged was sent; acknowledgements on
    # their way back: (arrives_s, robot, covers commands sent up to this time)
    unacked: dict[str, deque[float]] = {robot: deque() for robot in robots}
    next_ack_s = {robot: float(rng.uniform(0.0, ack_period_s)) for robot in robots}
    acks_in_flight: deque[tuple[float, str, float]] = deque()
    delivered = 0
    eps = 1e-9

    for robot, body in bodies.items():
        judge.on_pose(robot, 0.0, body.pose)
    step = 0
    now_s = 0.0
    while judge.result is None:
        for robot, body in bodies.items():
            while next_scan_s[robot] <= now_s + eps:
                if cut_off(robot, now_s, ("frozen",)) or cut_off(
                    robot, now_s + latency_s, readings_lost
                ):
                    next_scan_s[robot] += beam_period_s  # not taken, or lost on the way
                    continue
                for beam_deg, range_m in body.scan().items():
                    value = range_m if corrupt is None else corrupt(robot, beam_deg, now_s, range_m)
                    if value is not None:
                        beams_in_flight.append((now_s + latency_s, robot, beam_deg, value, now_s))
                next_scan_s[robot] += beam_period_s
        while beams_in_flight and beams_in_flight[0][0] <= now_s + eps:
            _, robot, beam_deg, value, stamp_s = beams_in_flight.popleft()
            delivered += planner.on_range(robot, beam_deg, value, stamp_s)
        for robot in robots:
            while next_ack_s[robot] <= now_s + eps:
                at_s = next_ack_s[robot]
                next_ack_s[robot] += ack_period_s
                if not (
                    cut_off(robot, at_s, commands_lost)
                    or cut_off(robot, at_s + latency_s, readings_lost)
                ):
                    # what was sent up to latency_s ago has arrived (or was resent and GAPed)
                    acks_in_flight.append((at_s + latency_s, robot, at_s - latency_s))
        while acks_in_flight and acks_in_flight[0][0] <= now_s + eps:
            _, robot, through_s = acks_in_flight.popleft()
            while unacked[robot] and unacked[robot][0] <= through_s + eps:
                unacked[robot].popleft()
        if next_tick_s <= now_s + eps:
            for robot in robots:
                planner.on_command_ack(robot, unacked[robot][0] if unacked[robot] else None)
            commands_in_flight.append((now_s + latency_s, planner.tick(now_s)))
            for robot in robots:
                unacked[robot].append(now_s)
            for event in planner.pop_events():
                judge.on_event(event)
            next_tick_s += tick_period_s
        while commands_in_flight and commands_in_flight[0][0] <= now_s + eps:
            for robot, command in commands_in_flight.popleft()[1].items():
                if not cut_off(robot, now_s, commands_lost):
                    bodies[robot].apply_command(command.v_m_s, command.omega_rad_s)
        if judge.result is not None or judge.check(now_s) is not None:
            break
        step += 1
        now_s = step * step_s
        for robot, body in bodies.items():
            if cut_off(robot, now_s, ("frozen",)):
                body.pause(step_s)
            else:
                body.step(step_s)
            judge.on_pose(robot, now_s, body.pose)

    return OfflineRun(
        result=judge.finish(now_s),
        paths=judge.paths(),
        events=list(judge.events),
        beams_delivered=delivered,
    )
