"""A real ROS 2 node (rclpy, on the RMW of ``RMW_IMPLEMENTATION``, Fast DDS by default) for the
bridge's rclpy backend test (tests/integration/test_ros2_rclpy_bridge.py), run as a process of
its own: ``python tests/integration/ros2_rclpy_peer.py --out FILE [--robot robot1]``, with
``ROS_DOMAIN_ID`` and ``ROS_AUTOMATIC_DISCOVERY_RANGE`` from the environment, as any ROS 2 node.

Written as a ROS 2 engineer would, from rclpy alone (no arpz): one node spun by its executor in a
thread. In order, it

1. subscribes to ``/<robot>/scan``, ``/<robot>/imu`` and ``/<robot>/front_scan`` with BEST_EFFORT
   (what the test's fleet offers), plus a RELIABLE subscription to ``/<robot>/imu`` and a
   BEST_EFFORT ``Twist`` publisher on ``/<robot>/cmd_vel`` whose QoS cannot match the bridge's,
   each with an incompatible-QoS event callback;
2. waits for ``--messages`` messages on each topic;
3. turns the robot: ``Twist`` (angular.z = 1 rad/s) on ``/<robot>/cmd_vel`` at 20 Hz for
   ``--turn-s`` seconds, from a RELIABLE publisher;
4. calls ``/<robot>/dock`` and ``/<robot>/jammed`` (``std_srvs/srv/Trigger``), as
   ``ros2 service call`` does;
5. writes one JSON object to ``--out``: every field of each message received (by topic), the QoS
   events, the services' responses, and the bridge's publishers' QoS as ROS 2's graph reports
   them (``get_publishers_info_by_topic``).

Exits 0 when it wrote the file, 1 with the reason on stderr when a step timed out.
"""

from __future__ import annotations

import argparse
import array
import json
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import rclpy
from geometry_msgs.msg import Twist
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Imu, LaserScan
from std_srvs.srv import Trigger


def as_dict(message: Any) -> Any:
    """Every field of a ROS 2 message, nested messages and arrays included, as JSON values."""
    if hasattr(message, "get_fields_and_field_types"):
        return {
            name: as_dict(getattr(message, name)) for name in message.get_fields_and_field_types()
        }
    if isinstance(message, (list, tuple, array.array)):
        return [as_dict(item) for item in message]
    if hasattr(message, "tolist"):  # numpy arrays (fixed-size fields)
        return message.tolist()
    return message


def wait(what: str, done: Callable[[], bool], timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not done():
        if time.monotonic() > deadline:
            print(f"ros2_rclpy_peer: timed out waiting for {what}", file=sys.stderr, flush=True)
            raise SystemExit(1)
        time.sleep(0.02)


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", required=True)
    parser.add_argument("--robot", default="robot1")
    parser.add_argument("--messages", type=int, default=15)
    parser.add_argument("--turn-s", type=float, default=2.5)
    parser.add_argument("--timeout-s", type=float, default=20.0)
    args = parser.parse_args()
    prefix = f"/{args.robot}"

    rclpy.init()
    node = Node("arpz_test_peer")
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    lock = threading.Lock()
    received: dict[str, list[Any]] = {"scan": [], "imu": [], "front_scan": []}
    events: list[dict[str, Any]] = []

    def keep(topic: str) -> Callable[[Any], None]:
        def on_message(message: Any) -> None:
            with lock:
                received[topic].append(as_dict(message))

        return on_message

    def event(role: str) -> Callable[[Any], None]:
        def on_event(info: Any) -> None:
            with lock:
                events.append(
                    {
                        "role": role,
                        "policy": info.last_policy_kind.name,
                        "total_count": info.total_count,
                    }
                )

        return on_event

    best_effort = QoSProfile(depth=50, reliability=ReliabilityPolicy.BEST_EFFORT)
    reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(LaserScan, f"{prefix}/scan", keep("scan"), best_effort)
    node.create_subscription(Imu, f"{prefix}/imu", keep("imu"), best_effort)
    node.create_subscription(LaserScan, f"{prefix}/front_scan", keep("front_scan"), best_effort)
    node.create_subscription(
        Imu,
        f"{prefix}/imu",
        lambda message: None,
        reliable,
        event_callbacks=SubscriptionEventCallbacks(incompatible_qos=event("subscription")),
    )
    node.create_publisher(
        Twist,
        f"{prefix}/cmd_vel",
        best_effort,
        event_callbacks=PublisherEventCallbacks(incompatible_qos=event("publisher")),
    )
    cmd_vel = node.create_publisher(Twist, f"{prefix}/cmd_vel", reliable)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    try:
        for topic, messages in received.items():
            wait(
                f"{args.messages} messages on {prefix}/{topic}",
                lambda messages=messages: len(messages) >= args.messages,
                args.timeout_s,
            )
        wait(
            "the bridge's subscription of cmd_vel", lambda: cmd_vel.get_subscription_count() > 0, 10
        )
        twist = Twist()
        twist.angular.z = 1.0
        turned_from = time.time_ns()
        end = time.monotonic() + args.turn_s
        while time.monotonic() < end:
            cmd_vel.publish(twist)
            time.sleep(0.05)
        turned_to = time.time_ns()

        services = {}
        for name in ("dock", "jammed"):
            client = node.create_client(Trigger, f"{prefix}/{name}")
            if not client.wait_for_service(timeout_sec=10.0):
                print(f"ros2_rclpy_peer: no service {prefix}/{name}", file=sys.stderr)
                return 1
            future = client.call_async(Trigger.Request())
            wait(f"the response of {prefix}/{name}", future.done, 10.0)
            services[name] = as_dict(future.result())
        wait("the incompatible-QoS events", lambda: len(events) >= 2, 5.0)
        graph = {
            topic: [
                {
                    "node": info.node_name,
                    "type": info.topic_type,
                    # what DDS discovery carries (history and depth are the writer's own)
                    "reliability": info.qos_profile.reliability.name,
                    "durability": info.qos_profile.durability.name,
                    "liveliness": info.qos_profile.liveliness.name,
                    "deadline_ns": info.qos_profile.deadline.nanoseconds,
                }
                for info in node.get_publishers_info_by_topic(f"{prefix}/{topic}")
            ]
            for topic in received
        }
        with lock:
            result = {
                "received": received,
                "events": events,
                "services": services,
                "graph": graph,
                "turned_ns": [turned_from, turned_to],
            }
        with open(args.out, "w", encoding="utf-8") as out:
            json.dump(result, out)  # inf and NaN as JSON's Infinity / NaN
    finally:
        executor.shutdown()
        spinner.join(timeout=5.0)
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
