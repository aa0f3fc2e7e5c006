"""The hallway mission of seed 001 section 3.2 (Figure 16) as ROS 2 nodes in rclpy: the same
``arpz.mission`` body, LIDAR, planner and judge as arpz's robot and CEDDP run, so the only
difference is the middleware.

    python -m arpz.experiment.ros2.mission_node --role robot --robot robot1 \\
        --world hallway_small --rate-hz 100 --depth 1 --seed 101 --out robot1.json
    python -m arpz.experiment.ros2.mission_node --role planner --world hallway_small \\
        --rate-hz 100 --depth 1 --time-limit-s 60 --max-age-s 0.3 --out planner.json

- ``--role robot``: a ``RobotBody`` in the world on a ``SimClock`` (arpz.robot.sim_host's),
  stepped at 50 Hz; its 8 beams published on ``/ROBOT/lidar_0`` ... ``/ROBOT/lidar_315`` at
  the cell's rate, one ``sensor_msgs/msg/Range`` a beam (``range`` quantised to 1 cm as arpz's
  beam driver does, ``header.stamp`` the scan's wall time: the source stamp the planner needs,
  which a bare Float32 would not carry); its true pose as ``geometry_msgs/msg/PoseStamped`` on
  ``/ROBOT/pose`` at 10 Hz (for the judge only); ``geometry_msgs/msg/Twist`` on
  ``/ROBOT/cmd_vel`` drives the body, with arpz's command watchdog (``CommandWatchdog``, 0.5 s
  for velocity: a stop when commands stop coming) besides the body's own motor timeout.
- ``--role planner``: ``HallwayPlanner`` fed every Range as it arrives (value and source stamp,
  as arpz's CEDDP feeds it a reading), ticked at 20 Hz with a Twist to every robot; the
  ``Judge`` on the true poses and the planner's events, started once every robot's pose has
  arrived (arpz starts it when every robot has joined). The planner is told of each robot's
  command acknowledgements only with ``--command-acks dds`` (the DDS writer's own:
  ``wait_for_all_acked`` with no wait, ``AckTracker``): Fast DDS acknowledges on its heartbeat
  (3 s by default), so in one loopback run 85 % of the ticks found a command unacknowledged and
  the fleet was held 45 % of the time. By default it is not told, as arpz's planner without a
  reliable channel.

QoS as the paper sets it for the beams: RELIABLE, VOLATILE, KEEP_LAST(depth), DEADLINE = the
beam period, both ends. Commands: RELIABLE KEEP_LAST 10 with a 0.5 s lifespan (arpz's command
traffic profile); poses: RELIABLE KEEP_LAST 10. One ``Node`` per process, its
``SingleThreadedExecutor`` spinning in its own thread; the robot's loop (body, beams, pose) is
the main thread. Each process prints ``ready`` when its endpoints exist; the planner prints
``mission started`` and ``mission verdict: ...``; SIGINT or SIGTERM stops a process, which then
writes its counters (and the planner its verdict) as JSON to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import queue
import sys
import threading
import time
from array import array
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
from geometry_msgs.msg import PoseStamped, Twist  # type: ignore[import-untyped]
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Range  # type: ignore[import-untyped]

from arpz.experiment.ros2.mission_parts import (
    AckTracker,
    Pacer,
    verdict_letter,
    yaw_of,
    yaw_quaternion,
)
from arpz.experiment.ros2.ros_process import RosProcess
from arpz.mission import BEAM_ANGLES_DEG, Lidar, Pose, RobotBody, SimClock, World, beam_topic
from arpz.mission.hallway import HallwayPlanner, PlannerSettings
from arpz.mission.judge import Judge, JudgeSettings, MissionResult
from arpz.robot.watchdog import CommandWatchdog

#: arpz's simulated robot: body steps, pose telemetry, the velocity watchdog (arpz.core.config
#: SimConfig's defaults and arpz.robot.agent's _SIM_VELOCITY_DEADLINE_S)
STEP_HZ = 50.0
TELEMETRY_HZ = 10.0
COMMAND_DEADLINE_S = 0.5
NOISE_STD_M = 0.01
#: arpz's command traffic profile (arpz.core.traffic): KEEP_LAST 10, a 0.5 s lifespan
COMMAND_DEPTH = 10
COMMAND_LIFESPAN_S = 0.5
TICK_HZ = 20.0
#: the longest the robot's loop sleeps: it must notice a stop and new commands quickly
MAX_SLEEP_S = 0.005


def beam_qos(depth: int, rate_hz: float) -> QoSProfile:
    """The paper's QoS for a sensor topic: RELIABLE, VOLATILE, KEEP_LAST(depth), DEADLINE the
    period at ``rate_hz``."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
        deadline=Duration(nanoseconds=round(1e9 / rate_hz)),
    )


def command_qos() -> QoSProfile:
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=COMMAND_DEPTH,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
        lifespan=Duration(nanoseconds=round(COMMAND_LIFESPAN_S * 1e9)),
    )


def pose_qos() -> QoSProfile:
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=10,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )


def _stamp_s(msg: Range | PoseStamped) -> float:
    return float(msg.header.stamp.sec) + float(msg.header.stamp.nanosec) / 1e9


def _set_stamp(msg: Range | PoseStamped, stamp_ns: int) -> None:
    msg.header.stamp.sec = stamp_ns // 1_000_000_000
    msg.header.stamp.nanosec = stamp_ns % 1_000_000_000


# ------------------------------------------------------------------------------------ robot


def run_robot(args: argparse.Namespace) -> dict[str, Any]:
    robot: str = args.robot
    world = World.load(args.world)
    body = RobotBody(world, robot, lidar=Lidar(world, noise_std_m=NOISE_STD_M, seed=args.seed))
    clock = SimClock()
    watchdog = CommandWatchdog({"velocity": COMMAND_DEADLINE_S})
    inbox: queue.SimpleQueue[tuple[float, float]] = queue.SimpleQueue()
    counts = {"commands_received": 0}

    spinner = RosProcess(f"{robot}_sim")
    node = spinner.node
    qos = beam_qos(args.depth, args.rate_hz)
    beams = {
        deg: node.create_publisher(Range, f"/{robot}/{beam_topic(deg)}", qos)
        for deg in BEAM_ANGLES_DEG
    }
    poses = node.create_publisher(PoseStamped, f"/{robot}/pose", pose_qos())

    def on_twist(msg: Twist) -> None:
        counts["commands_received"] += 1  # the executor's thread only
        inbox.put((float(msg.linear.x), float(msg.angular.z)))

    node.create_subscription(Twist, f"/{robot}/cmd_vel", on_twist, command_qos())
    spinner.start()
    print("ready", flush=True)

    start_s = time.monotonic()
    step, beam, telemetry = (Pacer(hz, start_s) for hz in (STEP_HZ, args.rate_hz, TELEMETRY_HZ))
    ranges = body.readings()
    applied = stops = beams_sent = poses_sent = write_failures = 0
    scan = Range()
    scan.radiation_type = Range.INFRARED
    scan.field_of_view = 0.01
    scan.min_range = 0.05
    scan.max_range = float(body.lidar.max_range_m)
    pose_msg = PoseStamped()
    pose_msg.header.frame_id = "map"
    while not spinner.stop.is_set():
        now_s = time.monotonic()
        if step.due(now_s):
            while True:
                try:
                    v_m_s, omega_rad_s = inbox.get_nowait()
                except queue.Empty:
                    break
                body.apply_command(v_m_s, omega_rad_s)
                watchdog.on_command("velocity", now_s)
                applied += 1
            if watchdog.check(now_s):
                body.apply_command(0.0, 0.0)  # arpz's safe stop
                stops += 1
            body.step(clock.tick())
            ranges = body.readings()
        if beam.due(now_s):
            stamp_ns = time.time_ns()
            for deg, publisher in beams.items():
                topic = beam_topic(deg)
                scan.header.frame_id = f"{robot}/{topic}"
                _set_stamp(scan, stamp_ns)
                scan.range = round(ranges[topic], 2)
                try:
                    publisher.publish(scan)
                except RuntimeError:  # RCLError: the RMW refused it (at 1000 Hz, depth 1000)
                    write_failures += 1
                    continue
                beams_sent += 1
        if telemetry.due(now_s):
            pose = body.pose
            _set_stamp(pose_msg, time.time_ns())
            pose_msg.pose.position.x = pose.x_m
            pose_msg.pose.position.y = pose.y_m
            pose_msg.pose.orientation.z, pose_msg.pose.orientation.w = yaw_quaternion(
                pose.theta_rad
            )
            poses.publish(pose_msg)
            poses_sent += 1
        wake_s = min(step.next_s, beam.next_s, telemetry.next_s)
        spinner.stop.wait(min(MAX_SLEEP_S, max(0.0, wake_s - time.monotonic())))
    elapsed_s = time.monotonic() - start_s
    spinner.close()
    pose = body.pose
    return {
        "role": "robot",
        "robot": robot,
        "rate_hz": args.rate_hz,
        "depth": args.depth,
        "elapsed_s": round(elapsed_s, 3),
        "beams_sent": beams_sent,
        "beams_due": round(elapsed_s * args.rate_hz) * len(BEAM_ANGLES_DEG),
        "beam_periods_skipped": beam.skipped,
        "beam_write_failures": write_failures,
        "poses_sent": poses_sent,
        "commands_received": counts["commands_received"],
        "commands_applied": applied,
        "watchdog_stops": stops,
        "collided": body.collided,
        "pose": [pose.x_m, pose.y_m, pose.theta_rad],
        "cpu_s": round(time.process_time(), 3),
    }


# ---------------------------------------------------------------------------------- planner


class PlannerState:
    """The planner and the judge behind one lock (readings and poses arrive on the executor's
    thread, ticks run on the main thread), as arpz's ``MissionRunner``."""

    def __init__(self, world: World, time_limit_s: float, max_age_s: float) -> None:
        self.settings = PlannerSettings.for_world(world, max_age_s=max_age_s)
        self.planner = HallwayPlanner(self.settings)
        self.judge = Judge(
            world,
            JudgeSettings(
                time_limit_s=time_limit_s,
                obstacle_range_m=self.settings.obstacle_range_m,
                max_range_m=self.settings.max_range_m,
            ),
        )
        self.lock = threading.Lock()
        self.robots = self.settings.robots
        self.started_s: float | None = None
        self.result: MissionResult | None = None
        self.beams_received = dict.fromkeys(self.robots, 0)
        self.poses_received = dict.fromkeys(self.robots, 0)
        self.events: list[str] = []
        #: per beam received, seconds from its source stamp to its arrival (the wall clock is
        #: the host's in every namespace of the lab)
        self.latencies_s = array("f")

    def on_range(self, robot: str, beam_deg: int, msg: Range) -> None:
        stamp_s = _stamp_s(msg)
        with self.lock:
            self.latencies_s.append(time.time() - stamp_s)
            self.beams_received[robot] += 1
            self.planner.on_range(robot, beam_deg, float(msg.range), stamp_s)

    def on_pose(self, robot: str, msg: PoseStamped) -> None:
        q = msg.pose.orientation
        pose = Pose(float(msg.pose.position.x), float(msg.pose.position.y), yaw_of(q.z, q.w))
        with self.lock:
            self.poses_received[robot] += 1
            if self.started_s is not None and self.result is None:
                self._conclude(self.judge.on_pose(robot, _stamp_s(msg), pose))

    def tick(self, now_s: float, acks: dict[str, float | None]) -> dict[str, tuple[float, float]]:
        """STOP for everyone before the start and after the verdict; else the planner's step
        (arpz.ceddp.mission.MissionRunner._tick)."""
        stop = dict.fromkeys(self.robots, (0.0, 0.0))
        with self.lock:
            if self.started_s is None and all(self.poses_received.values()):
                self.started_s = now_s
                self.judge.start_s = now_s
                print("mission started", flush=True)
            if self.started_s is None or self.result is not None:
                return stop
            for robot, since_s in acks.items():
                self.planner.on_command_ack(robot, since_s)
            commands = self.planner.tick(now_s)
            for event in self.planner.pop_events():
                self.events.append(f"{event.t_s - self.started_s:.2f} {event.kind}: {event.text}")
                self._conclude(self.judge.on_event(event))
            self._conclude(self.judge.check(now_s))
            if self.result is not None:
                return stop
            return {robot: (c.v_m_s, c.omega_rad_s) for robot, c in commands.items()}

    def finish(self, now_s: float) -> None:
        with self.lock:
            if self.result is None and self.started_s is not None:
                self._conclude(self.judge.finish(now_s))

    def _conclude(self, result: MissionResult | None) -> None:
        if result is None or self.result is not None:
            return
        self.result = result
        print(
            f"mission verdict: {verdict_letter(msgspec.to_builtins(result))} "
            f"{result.mission}: {result.reason}",
            flush=True,
        )


def offered_qos(node: Node, topic: str) -> list[dict[str, Any]]:
    """The QoS each publisher of ``topic`` offers, as ROS 2's graph (discovery) reports it: what
    the robots really set, seen from the planner's side of the link (DDS does not send the
    history depth, which the graph reports as 0)."""
    return [
        {
            "reliability": info.qos_profile.reliability.name,
            "durability": info.qos_profile.durability.name,
            "history": info.qos_profile.history.name,
            "deadline_ns": info.qos_profile.deadline.nanoseconds,
        }
        for info in node.get_publishers_info_by_topic(topic)
    ]


def _percentiles_ms(values_s: array[float]) -> dict[str, float] | None:
    """p50, p99 and max of the beams' latencies, in ms (None: no beam arrived)."""
    if not values_s:
        return None
    p50, p99 = np.percentile(np.frombuffer(values_s, dtype=np.float32), [50, 99])
    return {
        "p50": round(float(p50) * 1e3, 2),
        "p99": round(float(p99) * 1e3, 2),
        "max": round(max(values_s) * 1e3, 2),
    }


def _all_acked(publisher: Publisher[Any]) -> bool:
    return bool(publisher.wait_for_all_acked(Duration(nanoseconds=0)))


def run_planner(args: argparse.Namespace) -> dict[str, Any]:
    world = World.load(args.world)
    state = PlannerState(world, args.time_limit_s, args.max_age_s)
    spinner = RosProcess("hallway_planner")
    node = spinner.node
    qos = beam_qos(args.depth, args.rate_hz)
    for robot in state.robots:
        for deg in BEAM_ANGLES_DEG:
            node.create_subscription(
                Range,
                f"/{robot}/{beam_topic(deg)}",
                lambda msg, r=robot, d=deg: state.on_range(r, d, msg),
                qos,
            )
        node.create_subscription(
            PoseStamped, f"/{robot}/pose", lambda msg, r=robot: state.on_pose(r, msg), pose_qos()
        )
    commands = {
        robot: node.create_publisher(Twist, f"/{robot}/cmd_vel", command_qos())
        for robot in state.robots
    }
    trackers = {robot: AckTracker() for robot in state.robots}
    spinner.start()
    print("ready", flush=True)

    sent = 0
    offered: list[dict[str, Any]] = []
    ticks = Pacer(TICK_HZ, time.monotonic())
    twist = Twist()
    while not spinner.stop.is_set():
        if not ticks.due(time.monotonic()):
            spinner.stop.wait(max(0.0, ticks.next_s - time.monotonic()))
            continue
        now_s = time.time()
        acks: dict[str, float | None] = {}
        if args.command_acks == "dds":
            acks = {r: trackers[r].poll(_all_acked(commands[r])) for r in state.robots}
        if not offered and state.started_s is not None:
            offered = offered_qos(node, f"/{state.robots[0]}/{beam_topic(BEAM_ANGLES_DEG[0])}")
        for robot, (v_m_s, omega_rad_s) in state.tick(now_s, acks).items():
            twist.linear.x, twist.angular.z = v_m_s, omega_rad_s
            commands[robot].publish(twist)
            trackers[robot].sent(now_s)
            sent += 1
    state.finish(time.time())
    spinner.close()
    result = msgspec.to_builtins(state.result) if state.result is not None else None
    return {
        "role": "planner",
        "rate_hz": args.rate_hz,
        "depth": args.depth,
        "started": state.started_s is not None,
        "result": result,
        "verdict": verdict_letter(result),
        "beams_received": state.beams_received,
        "beam_latency_ms": _percentiles_ms(state.latencies_s),
        "poses_received": state.poses_received,
        "commands_sent": sent,
        "beam_qos_offered": offered,
        "tick_periods_skipped": ticks.skipped,
        "command_acks": args.command_acks,
        "ack_polls": {r: t.polls for r, t in trackers.items()},
        "ack_polls_unacknowledged": {r: t.unacknowledged_polls for r, t in trackers.items()},
        "events": state.events,
        "cpu_s": round(time.process_time(), 3),
    }


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m arpz.experiment.ros2.mission_node")
    parser.add_argument("--role", choices=("robot", "planner"), required=True)
    parser.add_argument("--robot", default="robot1", help="the robot's name (--role robot)")
    parser.add_argument("--world", default="hallway_small")
    parser.add_argument("--rate-hz", type=float, required=True, help="beams per second a topic")
    parser.add_argument("--depth", type=int, required=True, help="KEEP_LAST depth of the beams")
    parser.add_argument("--seed", type=int, default=1, help="the LIDAR noise's seed")
    parser.add_argument("--time-limit-s", type=float, default=60.0)
    parser.add_argument("--max-age-s", type=float, default=0.3)
    parser.add_argument(
        "--command-acks",
        choices=("none", "dds"),
        default="none",
        help="tell the planner how far each robot acknowledged its commands from the DDS "
        "writer's acknowledgements (dds), or not (none: it holds for readings only, as arpz's "
        "planner without a reliable channel)",
    )
    parser.add_argument("--out", type=Path, required=True, help="the counters' JSON file")
    args = parser.parse_args(argv)
    if not args.rate_hz > 0 or args.depth < 1:
        parser.error("--rate-hz must be > 0 and --depth >= 1")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    report = run_robot(args) if args.role == "robot" else run_planner(args)
    args.out.write_text(json.dumps(report, indent=1), encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
