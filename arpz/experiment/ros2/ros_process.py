"""One rclpy node per process, as the experiment's ROS 2 nodes run it: a node, a
``SingleThreadedExecutor`` spinning in its own thread, and SIGINT/SIGTERM setting ``stop``.

rclpy's own signal handlers are off: on a signal the node must write its counters first, then
shut rclpy down (``close``), or a cell loses what the node measured.
"""

from __future__ import annotations

import signal
import threading

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

#: how long ``close`` waits for the executor and its thread
CLOSE_TIMEOUT_S = 5.0


class RosProcess:
    """rclpy initialised without its signal handlers, one node, its executor in a thread."""

    def __init__(self, name: str) -> None:
        self.stop = threading.Event()
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda _signum, _frame: self.stop.set())
        rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
        self.node: Node = rclpy.create_node(name)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, name="ros-spin", daemon=True)

    def start(self) -> None:
        self.thread.start()

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=CLOSE_TIMEOUT_S)
        self.thread.join(timeout=CLOSE_TIMEOUT_S)
        self.node.destroy_node()
        rclpy.try_shutdown()
