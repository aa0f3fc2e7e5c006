"""One process of ``benchmarks/vs_ros2.py``: the perf tool's own ``pub``, ``sub``, ``ping`` and
``pong`` (``python -m arpz.perf``), with rclpy in place of Zenoh for ``rclpy``.

    python benchmarks/vs_ros2_node.py rclpy sub --connect - --key vs/t --size 1024 \\
        --history keep_all
    python benchmarks/vs_ros2_node.py zenoh pub --connect tcp/127.0.0.1:7447 --transport arpz ...

Every middleware is measured by the same loops, clocks and report: the perf tool's
(``arpz.perf.__main__``: the paced or flat-out publishing loop, the process CPU time of
publisher and subscriber, the end marker that gives the subscriber the count sent, the
sequence numbers and send stamps in the first 16 bytes of every payload). With ``rclpy``,
its endpoint factories and end marker are swapped for the rclpy ones below (``--connect`` and
``--transport`` are then unused, the report says ``rclpy``), as a ROS 2 engineer writes them:

- one ``Node`` a process, its ``SingleThreadedExecutor`` spinning in its own thread
  (``spin``, not ``spin_once`` a message); the publishing loop is the main thread;
- the payload as ``std_msgs/msg/UInt8MultiArray``, or ``sensor_msgs/msg/Image`` (640 x 480
  ``rgb8``, ``header.stamp`` the send stamp) for a 921 600-byte frame; one message object is
  kept and its ``data`` set from an ``array('B')`` (the generated setter's fast path: any other
  sequence is checked element by element);
- the QoS mapped from the perf tool's flags: RELIABLE (or BEST_EFFORT), KEEP_ALL or
  KEEP_LAST(depth), VOLATILE (or TRANSIENT_LOCAL); losses from ROS 2's own ``message_lost``
  event; a publisher's end waits for ``wait_for_all_acked``;
- the end marker on ``KEY/perf/end`` as ``std_msgs/msg/UInt64``, RELIABLE TRANSIENT_LOCAL.

Fast DDS keeps its defaults; the runner sets only the environment the measurement needs
(``ROS_DOMAIN_ID``, ``FASTDDS_BUILTIN_TRANSPORTS=UDPv4``, ``ROS_STATIC_PEERS`` in the lab).

With ``zenoh`` (arpz and raw Zenoh) nothing is swapped; both modes print ``<role>: matched``
on stderr once a publisher has matched, so the runner can impair the link after the sessions
opened and before the first sample.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from array import array
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import arpz.perf.__main__ as perf  # noqa: E402
from arpz.core.protocol.qos import (  # noqa: E402
    DurabilityPolicy,
    HistoryPolicy,
    QosProfile,
    ReliabilityPolicy,
)
from arpz.perf import report  # noqa: E402
from arpz.perf.endpoints import STOP, OnPayload, Pub, Sub  # noqa: E402
from arpz.perf.report import HEADER, Recorder, Report  # noqa: E402

#: a 640 x 480 rgb8 camera frame goes as sensor_msgs/msg/Image
IMAGE_WIDTH, IMAGE_HEIGHT, IMAGE_CHANNELS = 640, 480, 3
IMAGE_BYTES = IMAGE_WIDTH * IMAGE_HEIGHT * IMAGE_CHANNELS
#: what the runner waits for on stderr before it impairs the link
MATCHED = "matched"


def topic(key: str) -> str:
    """The perf tool's key as a ROS 2 topic name."""
    return "/" + key.strip("/")


def ros_qos(qos: QosProfile) -> Any:
    """The perf tool's QoS flags as rclpy's profile (the fields both have)."""
    from rclpy.qos import (
        DurabilityPolicy as RosDurability,
    )
    from rclpy.qos import (
        HistoryPolicy as RosHistory,
    )
    from rclpy.qos import (
        QoSProfile,
    )
    from rclpy.qos import (
        ReliabilityPolicy as RosReliability,
    )

    keep_all = qos.history is HistoryPolicy.KEEP_ALL
    return QoSProfile(
        history=RosHistory.KEEP_ALL if keep_all else RosHistory.KEEP_LAST,
        depth=qos.depth,
        reliability=RosReliability.RELIABLE
        if qos.reliability is ReliabilityPolicy.RELIABLE
        else RosReliability.BEST_EFFORT,
        durability=RosDurability.TRANSIENT_LOCAL
        if qos.durability is DurabilityPolicy.TRANSIENT_LOCAL
        else RosDurability.VOLATILE,
    )


class RosProcess:
    """The process's one node and its executor spinning in a thread; shut down when the last
    endpoint closes."""

    _instance: RosProcess | None = None

    def __init__(self) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        # the perf tool's own SIGINT/SIGTERM handlers stay (they set STOP)
        rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node(f"arpz_vs_ros2_{threading.get_native_id()}")
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, name="ros-spin", daemon=True)
        self.thread.start()
        self.users = 0

    @classmethod
    def acquire(cls) -> RosProcess:
        if cls._instance is None:
            cls._instance = cls()
        cls._instance.users += 1
        return cls._instance

    def release(self) -> None:
        import rclpy

        self.users -= 1
        if self.users > 0:
            return
        RosProcess._instance = None
        self.executor.shutdown()
        self.thread.join(timeout=5)
        self.node.destroy_node()
        rclpy.shutdown()


class Message:
    """The one message a publisher keeps: UInt8MultiArray, or Image for a camera frame."""

    def __init__(self, size: int) -> None:
        self.image = size == IMAGE_BYTES
        if self.image:
            from sensor_msgs.msg import Image

            self.msg: Any = Image(
                height=IMAGE_HEIGHT,
                width=IMAGE_WIDTH,
                encoding="rgb8",
                step=IMAGE_WIDTH * IMAGE_CHANNELS,
            )
        else:
            from std_msgs.msg import UInt8MultiArray

            self.msg = UInt8MultiArray()

    @staticmethod
    def type_for(size: int) -> Any:
        if size == IMAGE_BYTES:
            from sensor_msgs.msg import Image

            return Image
        from std_msgs.msg import UInt8MultiArray

        return UInt8MultiArray

    def fill(self, payload: bytes | array[int]) -> Any:
        self.msg.data = array("B", payload)
        if self.image:
            _, stamp_ns = HEADER.unpack_from(payload)
            self.msg.header.stamp.sec, self.msg.header.stamp.nanosec = divmod(stamp_ns, 10**9)
        return self.msg


class RclpyPub:
    def __init__(self, key: str, qos: QosProfile, size: int) -> None:
        self.ros = RosProcess.acquire()
        self.message = Message(size)
        self.pub = self.ros.node.create_publisher(Message.type_for(size), topic(key), ros_qos(qos))
        self.blocked = 0

    def wait_matched(self, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and not STOP.is_set():
            if self.pub.get_subscription_count() > 0:
                print(f"rclpy pub: {MATCHED}", file=sys.stderr, flush=True)
                return True
            time.sleep(0.02)
        return False

    def put(self, payload: bytes | array[int]) -> None:
        msg = self.message.fill(payload)
        while True:
            try:
                self.pub.publish(msg)
                return
            except Exception:  # KEEP_ALL's history full past its blocking time: retried
                self.blocked += 1
                if STOP.is_set():
                    raise

    def finish(self, linger_s: float) -> dict[str, Any]:
        from rclpy.duration import Duration

        acked = self.pub.wait_for_all_acked(Duration(nanoseconds=int(linger_s * 1e9)))
        return {"acknowledged": bool(acked), "blocked_timeouts": self.blocked}

    def close(self) -> None:
        self.ros.node.destroy_publisher(self.pub)
        self.ros.release()


class RclpySub:
    def __init__(self, key: str, qos: QosProfile, size: int, on_payload: OnPayload) -> None:
        from rclpy.event_handler import SubscriptionEventCallbacks

        self.ros = RosProcess.acquire()
        self._lost = 0

        def on_lost(info: Any) -> None:
            self._lost = int(info.total_count)

        def on_msg(msg: Any) -> None:
            on_payload(msg.data)  # an array('B'): the Recorder reads its header in place

        self.sub = self.ros.node.create_subscription(
            Message.type_for(size),
            topic(key),
            on_msg,
            ros_qos(qos),
            event_callbacks=SubscriptionEventCallbacks(message_lost=on_lost),
        )

    def lost(self) -> int:
        return self._lost

    def counters(self) -> dict[str, int]:
        return {"lost": self._lost}

    def close(self) -> None:
        self.ros.node.destroy_subscription(self.sub)
        self.ros.release()


class RclpyEndMarker:
    """The perf tool's end marker as a ROS 2 topic: the publisher's count, latched."""

    def __init__(self, args: argparse.Namespace) -> None:
        from rclpy.qos import DurabilityPolicy as RosDurability
        from rclpy.qos import QoSProfile
        from std_msgs.msg import UInt64

        self.ros = RosProcess.acquire()
        self.topic = topic(f"{args.key}/perf/end")
        self.qos = QoSProfile(depth=1, durability=RosDurability.TRANSIENT_LOCAL)
        self.type = UInt64
        self.count: int | None = None
        self.pub: Any = None
        self.sub: Any = None
        if args.command == "pub":  # declared now: matched by the time the run ends
            self.pub = self.ros.node.create_publisher(UInt64, self.topic, self.qos)

    def announce(self, count: int) -> None:
        for _ in range(5):
            self.pub.publish(self.type(data=count))
            time.sleep(0.05)

    def listen(self) -> None:
        def on_end(msg: Any) -> None:
            self.count = int(msg.data)

        self.sub = self.ros.node.create_subscription(self.type, self.topic, on_end, self.qos)

    def close(self) -> None:
        if self.pub is not None:
            self.ros.node.destroy_publisher(self.pub)
        if self.sub is not None:
            self.ros.node.destroy_subscription(self.sub)
        self.ros.release()


def use_rclpy() -> None:
    """Swap the perf tool's endpoints for rclpy's."""

    def make_pub(args: argparse.Namespace, key: str) -> Pub:
        return RclpyPub(key, perf.qos_from_args(args), args.size)

    def make_sub(args: argparse.Namespace, key: str, on_payload: OnPayload) -> Sub:
        return RclpySub(key, perf.qos_from_args(args), args.size, on_payload)

    def build_report(rec: Recorder, **fields: Any) -> Report:
        return report.build_report(rec, **(fields | {"transport": "rclpy"}))  # not --transport

    perf.make_pub = make_pub
    perf.make_sub = make_sub
    perf.EndMarker = RclpyEndMarker  # type: ignore[misc,assignment]
    setattr(perf, "build_report", build_report)  # noqa: B010 (imported there, not exported)


def announce_matching() -> None:
    """Print ``matched`` once a Zenoh or arpz publisher has matched."""
    make_pub: Callable[[argparse.Namespace, str], Pub] = perf.make_pub

    class Announcing:
        def __init__(self, inner: Pub) -> None:
            self.inner = inner

        def wait_matched(self, timeout_s: float) -> bool:
            matched = self.inner.wait_matched(timeout_s)
            if matched:
                print(f"zenoh pub: {MATCHED}", file=sys.stderr, flush=True)
            return matched

        def __getattr__(self, name: str) -> Any:
            return getattr(self.inner, name)

    perf.make_pub = lambda args, key: Announcing(make_pub(args, key))


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] not in ("rclpy", "zenoh"):
        print("usage: vs_ros2_node.py {rclpy|zenoh} PERF-ARGS...", file=sys.stderr)
        return 2
    if argv[0] == "rclpy":
        use_rclpy()
    else:
        announce_matching()
    return perf.main(argv[1:])


if __name__ == "__main__":
    sys.exit(main())
