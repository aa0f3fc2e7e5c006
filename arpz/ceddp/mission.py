"""The hallway mission on the CEDDP (seed 001 section 3.2), wired to the network.

Two parts that must not see each other's inputs: the ``HallwayPlanner`` gets only the LIDAR
readings that reached the CEDDP and passed cache control (so stale, late or lost data affects it
as it would on real robots), and drives the fleet through ``cmd/velocity`` at ``tick_hz``; the
``Judge`` gets the robots' TRUE poses from the telemetry key and the planner's events, and gives
the verdict. The runner has its own tick thread; readings arrive on the ingest worker and poses
on the control worker, so one lock guards planner and judge.

Besides the readings, the planner learns at every tick how long each robot has left its
velocity commands unacknowledged (``command_acks``: the downlink's reliable-channel writers,
``Downlink.unacknowledged_s``), and holds the fleet when one has for longer than
``PlannerSettings.max_command_age_s``: a robot whose commands are lost while its readings still
arrive is not obeying the plan the others follow.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import msgspec
import numpy as np

from arpz.ceddp.planner import CommandSink, Planner, Reading
from arpz.core.config import MissionConfig
from arpz.core.errors import ArpzError
from arpz.core.frames import WorldView
from arpz.core.messages import Command, Telemetry, encode
from arpz.mission import BEAM_ANGLES_DEG, Pose, World, beam_endpoints, beam_of_topic
from arpz.mission.hallway import HallwayPlanner, PlannerSettings
from arpz.mission.judge import Judge, JudgeSettings, MissionResult

log = logging.getLogger(__name__)

#: (text, level) -> None: the server's event log
EventSink = Callable[[str, str], None]
#: robot -> seconds its oldest unacknowledged velocity command has waited (0.0: none), or None
#: when that cannot be known (no reliable channel)
CommandAcks = Callable[[str], float | None]


class MissionRunner(Planner):
    def __init__(
        self,
        config: MissionConfig,
        sink: CommandSink,
        writer: str,
        on_event: EventSink,
        *,
        on_result: Callable[[MissionResult], None] | None = None,
        on_view: Callable[[WorldView], None] | None = None,
        command_acks: CommandAcks | None = None,
    ) -> None:
        self.config = config
        self.world = World.load(config.world)
        self.settings = PlannerSettings.for_world(self.world, max_age_s=config.max_age_s)
        self.planner = HallwayPlanner(self.settings)
        self.judge = Judge(
            self.world,
            JudgeSettings(
                time_limit_s=config.time_limit_s,
                obstacle_range_m=self.settings.obstacle_range_m,
                max_range_m=self.settings.max_range_m,
            ),
        )
        self.sink = sink
        self.writer = writer
        self.on_event = on_event
        self.on_result = on_result
        self.on_view = on_view
        self.command_acks = command_acks
        #: per robot, the unacknowledged age of its commands at each tick of the mission (s)
        self._ack_ages: dict[str, list[float]] = {r: [] for r in self.settings.robots}
        self.result: MissionResult | None = None
        self.started_s: float | None = None
        self.commands_sent = 0
        self.telemetry_received = 0
        self._present: set[str] = set()
        self._ranges: dict[str, dict[int, float]] = {r: {} for r in self.settings.robots}
        self._poses: dict[str, Pose] = {}
        self._paths: dict[str, list[tuple[float, float]]] = {r: [] for r in self.settings.robots}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="arpz-mission", daemon=True)
        self._seqs: dict[str, int] = {}

    # -- Planner hooks --------------------------------------------------------------------------

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        with self._lock:
            if self.result is None and self.started_s is not None:
                self._conclude(self.judge.finish(time.time()))

    def on_reading(self, reading: Reading) -> None:
        beam = beam_of_topic(reading.topic)
        if beam is None or not isinstance(reading.value, float):
            return
        with self._lock:
            self.planner.on_range(reading.robot, beam, reading.value, reading.stamp_ns / 1e9)
            if reading.robot in self._ranges:
                self._ranges[reading.robot][beam] = reading.value

    wants_unchanged = True

    def on_unchanged(self, robot: str, topic: str, stamp_ns: int) -> None:
        """Cache control discarded a repeat: the beam still reads what the planner has, now."""
        beam = beam_of_topic(topic)
        with self._lock:
            value = self._ranges.get(robot, {}).get(beam) if beam is not None else None
            if beam is not None and value is not None:
                self.planner.on_range(robot, beam, value, stamp_ns / 1e9)

    def on_robot(self, robot: str, alive: bool) -> None:
        with self._lock:
            (self._present.add if alive else self._present.discard)(robot)
            if self.started_s is None and set(self.settings.robots) <= self._present:
                self.started_s = time.time()
                self.judge.start_s = self.started_s
                self.on_event(f"mission: all {len(self._present)} robots present, judging", "INFO")

    def on_telemetry(self, robot: str, telemetry: Telemetry) -> None:
        """True poses: for the judge and the drawing, never for the planner."""
        pose = Pose(telemetry.x_m, telemetry.y_m, telemetry.theta_rad)
        with self._lock:
            self.telemetry_received += 1
            self._poses[robot] = pose
            if robot in self._paths:
                self._paths[robot].append((pose.x_m, pose.y_m))
            if self.started_s is not None and self.result is None:
                verdict = self.judge.on_pose(robot, telemetry.stamp_ns / 1e9, pose)
                if verdict is not None:
                    self._conclude(verdict)

    # -- the tick thread ----------------------------------------------------------------------

    def _run(self) -> None:
        period_s = 1.0 / self.config.tick_hz
        next_s = time.monotonic()
        views_every = max(1, round(self.config.tick_hz / 2))  # 2 Hz: a world view is heavy
        ticks = 0
        while not self._stop.is_set():
            now_s = time.time()
            with self._lock:
                commands = self._tick(now_s)
            for robot, (v_m_s, omega_rad_s) in commands.items():
                self._send(robot, v_m_s, omega_rad_s)
            ticks += 1
            if self.on_view is not None and ticks % views_every == 0:
                self.on_view(self._view())
            next_s += period_s
            self._stop.wait(max(0.0, next_s - time.monotonic()))

    def _tick(self, now_s: float) -> dict[str, tuple[float, float]]:
        """Planner step under the lock; STOP for everyone before the start and after a verdict
        (the bodies' watchdog needs a command every tick)."""
        stop = {robot: (0.0, 0.0) for robot in self.settings.robots}
        if self.started_s is None or self.result is not None:
            return stop
        if self.command_acks is not None:
            for robot in self.settings.robots:
                age_s = self.command_acks(robot)
                if age_s is not None:
                    self._ack_ages[robot].append(age_s)
                self.planner.on_command_ack(robot, now_s - age_s if age_s else None)
        commands = self.planner.tick(now_s)
        for event in self.planner.pop_events():
            level = "WARN" if event.kind in ("stale_stop", "obstacle_stop", "off_lane") else "INFO"
            self.on_event(f"mission {event.kind}: {event.text}", level)
            verdict = self.judge.on_event(event)
            if verdict is not None:
                self._conclude(verdict)
        verdict = self.judge.check(now_s)
        if verdict is not None and self.result is None:
            self._conclude(verdict)
        if self.result is not None:
            return stop
        return {robot: (c.v_m_s, c.omega_rad_s) for robot, c in commands.items()}

    def _conclude(self, result: MissionResult) -> None:
        if self.result is not None:
            return
        self.result = result
        self.on_event(
            f"mission {result.mission}: {result.reason}",
            "INFO" if result.mission == "success" else "ERROR",
        )
        if self.on_result is not None:
            self.on_result(result)

    def _send(self, robot: str, v_m_s: float, omega_rad_s: float) -> None:
        # seq counts per key (docs/protocol.md): one counter per robot's cmd/velocity
        seq = self._seqs[robot] = self._seqs.get(robot, 0) + 1
        command = Command(self.writer, seq, time.time_ns(), [v_m_s, omega_rad_s])
        try:
            self.sink.send(robot, "velocity", encode(command))
            self.commands_sent += 1
        except ArpzError as exc:  # the session may be closing, or a full history refused it
            log.debug("velocity command not sent: %s", exc)

    def _view(self) -> WorldView:
        with self._lock:
            poses = dict(self._poses)
            rays: dict[str, list[tuple[float, float]]] = {}
            for robot, pose in poses.items():
                known = self._ranges.get(robot, {})
                if len(known) == len(BEAM_ANGLES_DEG):
                    ends = beam_endpoints(pose, [known[d] for d in BEAM_ANGLES_DEG])
                    rays[robot] = [(float(x), float(y)) for x, y in ends]
            paths = {robot: list(path) for robot, path in self._paths.items() if path}
        return WorldView(
            stamp_ns=time.time_ns(),
            poses={r: (p.x_m, p.y_m, p.theta_rad) for r, p in poses.items()},
            rays=rays,
            paths=paths,
        )

    def summary(self) -> dict[str, Any]:
        with self._lock:
            result = self.result
            return {
                "world": self.world.name,
                "result": msgspec.to_builtins(result) if result is not None else None,
                "started": self.started_s is not None,
                "commands_sent": self.commands_sent,
                "telemetry_received": self.telemetry_received,
                "events": len(self.judge.events),
                "command_ack_age_s": {
                    robot: _spread(ages) for robot, ages in self._ack_ages.items() if ages
                },
            }


def _spread(ages: list[float]) -> dict[str, float]:
    """p50, p99 and max of one robot's command acknowledgement ages, in seconds."""
    p50, p99 = np.percentile(ages, [50, 99])
    return {"p50": round(float(p50), 3), "p99": round(float(p99), 3), "max": round(max(ages), 3)}
