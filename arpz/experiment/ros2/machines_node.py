"""Seed 001's own application (section 3.1, Fig. 9) as ROS 2 nodes in rclpy: one process per
machine, as a ROS 2 engineer writes it, for the ``middleware = "ros2"`` cells of
``arpz.experiment``.

    python -m arpz.experiment.ros2.machines_node --role robot --name robot1 --preset machine1 \\
        --rate-hz 100 --depth 10 --seed 101 --hello-origin robot1 --hello-relay robot3 \\
        --counters robot1.json
    python -m arpz.experiment.ros2.machines_node --role ceddp \\
        --robots robot1=machine1,robot2=machine2,robot3=machine3 --rate-hz 100 --depth 10 \\
        --hello-origin robot1 --hello-relay robot3 --counters ceddp.json

- one ``Node`` per process, its ``SingleThreadedExecutor`` spinning in its own thread;
- a robot publishes each sensor of its machine preset (``arpz.robot.sensors.presets``) on
  ``/ROBOT/SENSOR`` from a timer at the cell's rate, the values read from arpz's own simulated
  drivers with the seeds arpz's robots use (``arpz.robot.sensors.factory.sensor_seed``), so
  both middlewares carry the same readings;
- every topic, sensor or Hello leg, has the cell's QoS as the paper sets it: RELIABLE,
  VOLATILE, KEEP_LAST(depth) and DEADLINE = the topic's period;
- the Hello of Fig. 9: the origin robot sends one every 1/hello_rate on ``/ORIGIN/hello``
  (stage 1); the CEDDP forwards it on ``/RELAY/cmd_hello``; the relay robot sends it back on
  ``/RELAY/hello`` (stage 2); the CEDDP returns it on ``/ORIGIN/cmd_hello`` (stage 3); a Hello
  not back within 2 s is lost (arpz's ``HelloTracker``, the same bookkeeping as arpz's robots);
- every message is a ``geometry_msgs/msg/PointStamped``: ``header.stamp`` the send time (wall
  clock: every namespace of the lab shares the host's), ``point.x`` the sequence number,
  ``point.y`` a numeric reading (or the Hello's stage), ``header.frame_id`` a text reading (or
  the Hello's origin). 40-50 bytes serialized, as small as arpz's msgpack samples, and a
  standard type any ROS 2 tool shows.

Each process prints ``ready`` once its endpoints exist and (robots) ``running`` once every
publisher matched the CEDDP's subscription and its timers started; SIGINT or SIGTERM stops the
timers, waits (bounded) for the publishers' samples to be acknowledged and the Hellos in flight,
writes the counters to ``--counters`` (JSON) and shuts rclpy down. The CEDDP keeps taking
samples until none came for ``QUIET_S`` before it writes its own.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from array import array
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from arpz.core.config import SensorConfig
from arpz.experiment.ros2.ros_process import RosProcess
from arpz.robot.hello import HelloTracker
from arpz.robot.sensors.base import SensorDriver
from arpz.robot.sensors.factory import make_driver
from arpz.robot.sensors.presets import PRESETS

#: a Hello not back after this long is lost (arpz's HelloConfig.timeout_s)
HELLO_TIMEOUT_S = 2.0
#: at the end, how long a publisher may wait for its samples to be acknowledged
ACK_WAIT_S = 3.0
#: the CEDDP stops when no sample came for this long after its stop was asked (or MAX_DRAIN_S)
QUIET_S = 0.5
MAX_DRAIN_S = 5.0
#: how long a robot waits for the CEDDP's subscriptions to match its publishers
MATCH_TIMEOUT_S = 60.0
#: after its publishers matched, before the first sample: the CEDDP's readers must have matched
#: the robot's writers too (a DATA from a writer a reader does not know yet is dropped, and
#: VOLATILE never resends it), as arpz's robots wait for their reliable channel to match
SETTLE_S = 1.0
#: Hello stages (seed 001 Fig. 9, as arpz.core.messages.Hello numbers them)
STAGE_ORIGIN, STAGE_RELAYED, STAGE_RETURNED = 1, 2, 3


def _stamp_ns(msg: Any) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def _set_stamp(msg: Any, ns: int) -> None:
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(ns, 1_000_000_000)


def point_stamped() -> Any:
    """geometry_msgs/msg/PointStamped, every message of the application."""
    from geometry_msgs.msg import PointStamped  # type: ignore[import-untyped]

    return PointStamped


def cell_qos(rate_hz: float, depth: int) -> Any:
    """The paper's profile: RELIABLE, VOLATILE, KEEP_LAST(depth), DEADLINE = 1 / rate."""
    from rclpy.duration import Duration
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
        deadline=Duration(nanoseconds=int(1e9 / rate_hz)),
    )


@dataclass
class SensorTopic:
    """One sensor of a robot: its driver, publisher, timer and counts."""

    name: str
    driver: SensorDriver
    publisher: Any
    msg: Any
    seq: int = 0
    produced: int = 0
    sent: int = 0
    timer: Any = None


class RobotNode:
    """A robot machine: its sensors on timers, and its part of the Hello."""

    def __init__(self, ros: RosProcess, args: argparse.Namespace) -> None:
        PointStamped = point_stamped()
        self.ros = ros
        self.name: str = args.name
        self.rate_hz: float = args.rate_hz
        self.qos = cell_qos(args.rate_hz, args.depth)
        self.hello_qos = cell_qos(args.hello_rate_hz, args.depth)
        self.started = time.monotonic()
        node = ros.node
        self.sensors = [
            SensorTopic(
                kind,
                make_driver(
                    SensorConfig(name=kind, kind=kind, rate_hz=args.rate_hz),  # type: ignore[arg-type]
                    robot_id=self.name,
                    robot_seed=args.seed,
                    base_dir=Path.cwd(),
                ),
                node.create_publisher(PointStamped, f"/{self.name}/{kind}", self.qos),
                PointStamped(),
            )
            for kind in PRESETS[args.preset]
        ]
        self.origin = args.hello_origin == self.name
        self.relay = args.hello_relay == self.name
        self.tracker = HelloTracker(HELLO_TIMEOUT_S)
        self.hello_rate_hz: float = args.hello_rate_hz
        self.hello_seq = 0
        self.hello_pub: Any = None
        self.hello_sub: Any = None
        self.hello_timer: Any = None
        self.hops_received = 0
        self.hello_msg = PointStamped()
        if self.origin or self.relay:
            self.hello_pub = node.create_publisher(
                PointStamped, f"/{self.name}/hello", self.hello_qos
            )
            self.hello_sub = node.create_subscription(
                PointStamped, f"/{self.name}/cmd_hello", self.on_hop, self.hello_qos
            )
        self.window_start: float | None = None
        self.window_end: float | None = None
        self.acked: bool | None = None
        #: held by a sensor timer's callback: the stop waits for the one in flight (the
        #: executor's thread), so produced and sent are read after its publish
        self._publishing = threading.Lock()
        self._stopped = False

    def publishers(self) -> list[Any]:
        return [s.publisher for s in self.sensors] + ([self.hello_pub] if self.hello_pub else [])

    def matched(self) -> bool:
        if any(p.get_subscription_count() < 1 for p in self.publishers()):
            return False
        return self.hello_sub is None or self.hello_sub.get_publisher_count() >= 1

    def start(self) -> None:
        """The timers: one per sensor at the cell's rate, the Hello's at the origin."""
        node = self.ros.node
        self.window_start = time.monotonic()
        for sensor in self.sensors:
            sensor.timer = node.create_timer(1.0 / self.rate_hz, self._publisher_of(sensor))
        if self.origin:
            self.hello_timer = node.create_timer(1.0 / self.hello_rate_hz, self.send_hello)

    def _publisher_of(self, sensor: SensorTopic) -> Any:
        def publish() -> None:
            with self._publishing:
                if self._stopped:
                    return  # dispatched before its timer was cancelled
                value = sensor.driver.read(time.monotonic() - self.started)
                sensor.produced += 1
                sensor.seq += 1
                msg = sensor.msg
                msg.point.x = float(sensor.seq)
                if isinstance(value, str):
                    msg.header.frame_id = value
                else:
                    msg.point.y = float(value)
                _set_stamp(msg, time.time_ns())
                sensor.publisher.publish(msg)
                sensor.sent += 1

        return publish

    def send_hello(self) -> None:
        self.hello_seq += 1
        t0_ns = time.time_ns()
        self.tracker.on_sent(self.hello_seq, t0_ns)
        msg = self.hello_msg
        msg.header.frame_id = self.name
        msg.point.x = float(self.hello_seq)
        msg.point.y = float(STAGE_ORIGIN)
        _set_stamp(msg, t0_ns)
        self.hello_pub.publish(msg)
        self.tracker.expire(time.time_ns())

    def on_hop(self, msg: Any) -> None:
        """A hop from the CEDDP: relay stage 1 as stage 2; record our own stage 3."""
        self.hops_received += 1
        stage = int(msg.point.y)
        if stage == STAGE_ORIGIN and self.relay:
            self.tracker.on_relayed()
            msg.point.y = float(STAGE_RELAYED)
            self.hello_pub.publish(msg)
        elif stage == STAGE_RETURNED and msg.header.frame_id == self.name:
            now_ns = time.time_ns()
            # past its timeout a Hello is lost, also when it returns before the next send's
            # expiry (or after the timers stopped): it then counts as late, not as a round trip
            self.tracker.expire(now_ns)
            self.tracker.on_returned(int(msg.point.x), now_ns)

    def stop(self) -> None:
        """Stop producing; wait (bounded) for the Hellos in flight, then for the samples'
        acknowledgements."""
        for timer in [s.timer for s in self.sensors] + [self.hello_timer]:
            if timer is not None:
                timer.cancel()
        with self._publishing:
            self._stopped = True
        self.window_end = time.monotonic()
        if self.origin:
            end = time.monotonic() + HELLO_TIMEOUT_S
            while self.tracker.outstanding and time.monotonic() < end:
                time.sleep(0.01)
            self.tracker.expire(time.time_ns(), all_outstanding=True)
        from rclpy.duration import Duration

        deadline = time.monotonic() + ACK_WAIT_S
        acked = True
        for publisher in self.publishers():
            left = max(0.0, deadline - time.monotonic())
            acked &= bool(publisher.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))))
        self.acked = acked

    def counters(self) -> dict[str, Any]:
        window = (self.window_end or time.monotonic()) - (self.window_start or time.monotonic())
        return {
            "role": "robot",
            "name": self.name,
            "rate_hz": self.rate_hz,
            "window_s": window,
            "acked": self.acked,
            "topics": {s.name: {"produced": s.produced, "sent": s.sent} for s in self.sensors},
            "hello": msgspec.structs.asdict(self.tracker.stats()) if self.origin else None,
            "hello_relayed": self.tracker.relayed,
            "hops_received": self.hops_received,
        }


@dataclass
class TopicIntake:
    """What the CEDDP took of one robot topic: sequence numbers seen and latencies (ms)."""

    received: int = 0
    duplicates: int = 0
    max_seq: int = 0
    seen: set[int] = field(default_factory=set)
    latency_ms: array[float] = field(default_factory=lambda: array("d"))


class CeddpNode:
    """The CEDDP: every robot topic subscribed, and the Hello relayed as Fig. 9 draws it."""

    def __init__(self, ros: RosProcess, args: argparse.Namespace) -> None:
        PointStamped = point_stamped()
        node = ros.node
        qos = cell_qos(args.rate_hz, args.depth)
        hello_qos = cell_qos(args.hello_rate_hz, args.depth)
        self.robots: dict[str, str] = dict(item.split("=", 1) for item in args.robots.split(","))
        self.topics: dict[str, TopicIntake] = {}
        self.last_sample = time.monotonic()
        self.subscriptions = []
        for robot, preset in self.robots.items():
            for kind in PRESETS[preset]:
                intake = self.topics[f"{robot}/{kind}"] = TopicIntake()
                self.subscriptions.append(
                    node.create_subscription(
                        PointStamped, f"/{robot}/{kind}", self._taker(intake), qos
                    )
                )
        self.origin: str = args.hello_origin
        self.relay: str = args.hello_relay
        self.hops_written = {self.origin: 0, self.relay: 0}
        self.hello_in = {self.origin: 0, self.relay: 0}
        self.down = {
            robot: node.create_publisher(PointStamped, f"/{robot}/cmd_hello", hello_qos)
            for robot in (self.origin, self.relay)
        }
        for robot in (self.origin, self.relay):
            self.subscriptions.append(
                node.create_subscription(
                    PointStamped, f"/{robot}/hello", self._hello_from(robot), hello_qos
                )
            )

    def _taker(self, intake: TopicIntake) -> Any:
        def take(msg: Any) -> None:
            now_ns = time.time_ns()
            seq = int(msg.point.x)
            if seq in intake.seen:
                intake.duplicates += 1
                return
            intake.seen.add(seq)
            intake.received += 1
            intake.max_seq = max(intake.max_seq, seq)
            intake.latency_ms.append((now_ns - _stamp_ns(msg)) / 1e6)
            self.last_sample = time.monotonic()

        return take

    def _hello_from(self, robot: str) -> Any:
        def on_hello(msg: Any) -> None:
            self.hello_in[robot] += 1
            stage = int(msg.point.y)
            if stage == STAGE_ORIGIN:
                target = self.relay
            elif stage == STAGE_RELAYED:
                target = msg.header.frame_id
                msg.point.y = float(STAGE_RETURNED)
            else:
                return
            if target in self.down:
                self.down[target].publish(msg)
                self.hops_written[target] += 1

        return on_hello

    def drain(self) -> None:
        """Keep taking until no sample came for QUIET_S (at most MAX_DRAIN_S)."""
        end = time.monotonic() + MAX_DRAIN_S
        while time.monotonic() < end and time.monotonic() - self.last_sample < QUIET_S:
            time.sleep(0.05)

    def counters(self) -> dict[str, Any]:
        robots: dict[str, Any] = {}
        for robot in self.robots:
            mine = {
                key.split("/", 1)[1]: intake
                for key, intake in self.topics.items()
                if key.startswith(robot + "/")
            }
            latencies = np.concatenate(
                [np.frombuffer(t.latency_ms, dtype=float) for t in mine.values()] or [np.zeros(0)]
            )
            p50, p99 = (
                (float(np.percentile(latencies, 50)), float(np.percentile(latencies, 99)))
                if latencies.size
                else (None, None)
            )
            robots[robot] = {
                "latency_ms_p50": p50,
                "latency_ms_p99": p99,
                "topics": {
                    name: {
                        "received": t.received,
                        "duplicates": t.duplicates,
                        "max_seq": t.max_seq,
                    }
                    for name, t in mine.items()
                },
            }
        return {
            "role": "ceddp",
            "robots": robots,
            "hello_in": self.hello_in,
            "hops_written": self.hops_written,
        }


def _wait_matched(robot: RobotNode, stop: threading.Event) -> bool:
    deadline = time.monotonic() + MATCH_TIMEOUT_S
    while time.monotonic() < deadline and not stop.is_set():
        if robot.matched():
            return True
        time.sleep(0.02)
    return False


def run(args: argparse.Namespace) -> int:
    ros = RosProcess(f"arpz_{args.role}_{args.name}".replace("-", "_"))
    counters: dict[str, Any]
    code = 0
    try:
        if args.role == "robot":
            robot = RobotNode(ros, args)
            ros.start()
            print("ready", flush=True)
            if not _wait_matched(robot, ros.stop):
                print(
                    f"{args.name}: the CEDDP's subscriptions did not match within "
                    f"{MATCH_TIMEOUT_S:g} s",
                    file=sys.stderr,
                    flush=True,
                )
                return 2
            ros.stop.wait(SETTLE_S)
            robot.start()
            print("running", flush=True)
            ros.stop.wait()
            robot.stop()
            counters = robot.counters()
        else:
            ceddp = CeddpNode(ros, args)
            ros.start()
            print("ready", flush=True)
            ros.stop.wait()
            ceddp.drain()
            counters = ceddp.counters()
    finally:
        ros.close()
    Path(args.counters).write_text(json.dumps(counters), encoding="utf-8")
    print("counters written", flush=True)
    return code


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m arpz.experiment.ros2.machines_node")
    parser.add_argument("--role", choices=("robot", "ceddp"), required=True)
    parser.add_argument("--name", default="ceddp", help="the robot's name (robot1...)")
    parser.add_argument("--preset", choices=sorted(PRESETS), help="the robot's machine")
    parser.add_argument(
        "--robots", default="", help="CEDDP: ROBOT=PRESET,... of every robot it subscribes"
    )
    parser.add_argument("--rate-hz", type=float, required=True)
    parser.add_argument("--depth", type=int, required=True)
    parser.add_argument("--seed", type=int, default=1, help="the robot's seed (arpz's)")
    parser.add_argument("--hello-rate-hz", type=float, default=10.0)
    parser.add_argument("--hello-origin", default="robot1")
    parser.add_argument("--hello-relay", default="robot3")
    parser.add_argument("--counters", required=True, help="where the JSON counters go")
    args = parser.parse_args(argv)
    if args.role == "robot" and not args.preset:
        parser.error("a robot needs --preset")
    if args.role == "ceddp" and not args.robots:
        parser.error("the CEDDP needs --robots")
    return run(args)


if __name__ == "__main__":
    sys.exit(main())
