"""The bridge's rclpy backend (``[ros2] backend = "rclpy"``, docs/ros2.md "Backends"): the fleet
as a real ROS 2 node, on whatever RMW the host's ROS 2 uses (Fast DDS by default,
``RMW_IMPLEMENTATION`` respected), so DDS-based ROS 2 systems see the robots too.

The only module of arpz that imports rclpy. ``RclpyBridge`` is the rmw_zenoh ``Bridge`` with
its node and entities swapped: the fleet side, the conversions and the worker are the same, and
the CDR the bridge already makes goes to rclpy as a serialized message (``publish`` of bytes:
no conversion to rclpy's classes, exact). Each bridged type needs its Python package
(``sensor_msgs.msg``, ``std_srvs.srv``, ...): one that does not import is not bridged, counted
``unknown_type``, as a type arpz does not know.

- the node runs in its own rclpy ``Context`` (initialised at ``start``, shut down at ``close``;
  no signal handlers: the host process keeps its own) with ``[ros2] domain_id`` as its domain,
  and its own ``SingleThreadedExecutor`` spun by one thread (``arpz-ros2-rclpy``);
- publishers and subscriptions are made and destroyed by the bridge's worker; a command
  subscription takes serialized messages (``raw=True``) and queues them for the worker;
- a service's callback is a coroutine: it queues the request's CDR for the worker, which calls
  the robot through ``ServiceCalls``, and awaits the answer without holding the executor (a
  guard condition wakes it when the call completes); a call that fails gets the std_srvs-style
  failure response where the type has one, else none (``_NoAnswer`` ends the callback);
- QoS: each publisher offers the QoS mapped from the topic's arpz profile
  (``rmw_zenoh.qos_from_profile`` with TRANSIENT_LOCAL kept: the RMW keeps the history for late
  joiners), each command subscription requests only the profile's reliability and history:
  deadline, liveliness and durability stay at their most accepting, so any ordinary publisher
  matches. The RMW's own incompatible-QoS events on the bridge's entities are counted
  (``qos_incompatible``) and logged; the ROS 2 side gets its own.
"""

from __future__ import annotations

import importlib
import logging
import threading
from collections.abc import Callable, Coroutine, Generator
from typing import Any, Final

import rclpy
from rclpy.context import Context
from rclpy.duration import Duration, Infinite
from rclpy.event_handler import (
    PublisherEventCallbacks,
    QoSOfferedIncompatibleQoSInfo,
    QoSRequestedIncompatibleQoSInfo,
    SubscriptionEventCallbacks,
)
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.guard_condition import GuardCondition
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    LivelinessPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_services_default,
)
from rclpy.serialization import deserialize_message, serialize_message
from rclpy.signals import SignalHandlerOptions

from arpz.bridge import rmw_zenoh
from arpz.bridge.bridge import Bridge, Port, TopicPort
from arpz.bridge.factory import INSTALL_HINT, Ros2Unavailable
from arpz.bridge.type_hash import UnknownTypeError
from arpz.core.config import Ros2CommandConfig
from arpz.core.errors import ArpzError
from arpz.core.throttled_log import ThrottledLog

log = logging.getLogger(__name__)
throttled = ThrottledLog(log)

#: rcl's arguments for the bridge's context: no log files of its own under ~/.ros/log (the host
#: process logs; rcl's console output still reaches stderr)
_ROS_ARGS: Final = ["--ros-args", "--disable-external-lib-logs"]
#: how long the executor waits for work before it looks at the stop flag, s
_SPIN_S: Final = 0.1


def interface_class(ros_type: str) -> Any:
    """The rclpy class of a message or service type (``sensor_msgs/msg/LaserScan``,
    ``std_srvs/srv/Trigger``) from its package's Python module; UnknownTypeError when the
    package does not import or has no such type."""
    parts = ros_type.split("/")
    if len(parts) != 3 or parts[1] not in ("msg", "srv"):
        raise UnknownTypeError(f"{ros_type!r} is not a ROS 2 message or service type name")
    package, sub, name = parts
    try:
        module = importlib.import_module(f"{package}.{sub}")
    except ImportError as exc:
        raise UnknownTypeError(
            f"{ros_type}: ROS 2's Python package {package} does not import here ({exc}): "
            f"install it (ros-{package.replace('_', '-')} from the package index, as "
            f"{INSTALL_HINT} does for the standard ones) or source its workspace"
        ) from None
    cls = getattr(module, name, None)
    if cls is None:
        raise UnknownTypeError(f"{ros_type}: package {package} has no {sub} {name}")
    return cls


def _duration(value: tuple[int, int]) -> Duration:
    if value == rmw_zenoh.INFINITE:
        return Infinite
    return Duration(seconds=value[0], nanoseconds=value[1])


def rclpy_qos(qos: rmw_zenoh.RmwQos) -> QoSProfile:
    """The rclpy profile of a bridged entity's QoS (the same rmw numbers)."""
    return QoSProfile(
        reliability=ReliabilityPolicy(qos.reliability),
        durability=DurabilityPolicy(qos.durability),
        history=HistoryPolicy(qos.history),
        depth=qos.depth,
        deadline=_duration(qos.deadline),
        lifespan=_duration(qos.lifespan),
        liveliness=LivelinessPolicy(qos.liveliness),
        liveliness_lease_duration=_duration(qos.lease),
    )


def command_qos(profile: Any) -> rmw_zenoh.RmwQos:
    """What a command subscription requests: the profile's reliability and history only (a
    request stricter than an ordinary publisher offers, say a deadline, would refuse it)."""
    offered = rmw_zenoh.qos_from_profile(profile)
    return rmw_zenoh.RmwQos(
        reliability=offered.reliability, history=offered.history, depth=offered.depth
    )


def _policy(info: QoSOfferedIncompatibleQoSInfo | QoSRequestedIncompatibleQoSInfo) -> str:
    kind = info.last_policy_kind
    return str(getattr(kind, "name", kind)).removeprefix("RMW_QOS_POLICY_")


class _NoAnswer(ArpzError):
    """Ends a service callback without a response (the robot's call failed, and the type has
    no failure response): caught around the executor."""


class _Answer:
    """A service call's answer, awaited by its callback on the executor's thread and set from
    another (the worker, or the transport's when the call completes)."""

    def __init__(self, wake: GuardCondition) -> None:
        self._wake = wake
        self._done = threading.Event()
        self._cdr: bytes | None = None

    def set(self, cdr: bytes | None) -> None:
        self._cdr = cdr
        self._done.set()
        try:
            self._wake.trigger()
        except Exception:  # the node is gone (closing): nobody waits any more
            log.debug("ROS 2 bridge: answer after close")

    def __await__(self) -> Generator[None, None, bytes | None]:
        while not self._done.is_set():
            yield
        return self._cdr


class _RclpyTopic:
    def __init__(self, node: Node, publisher: Any) -> None:
        self._node = node
        self._publisher = publisher

    def put(self, cdr: bytes, seq: int, stamp_ns: int) -> None:
        self._publisher.publish(cdr)  # a serialized message: the CDR as it is

    def close(self) -> None:
        self._node.destroy_publisher(self._publisher)


class _RclpyEntity:
    def __init__(self, close: Callable[[], object]) -> None:
        self._close = close

    def close(self) -> None:
        self._close()


class RclpyBridge(Bridge):
    """``Bridge``'s public surface (``start``, ``close``, ``stats``) on an rclpy node."""

    backend = "rclpy"

    _context: Context
    _node: Node
    _executor: SingleThreadedExecutor
    _wake: GuardCondition

    # -- the node --------------------------------------------------------------------------------

    def _start_node(self) -> None:
        """rclpy's context, the node and its executor's thread; Ros2Unavailable if ROS 2 does
        not start. (An RMW_IMPLEMENTATION that is not installed never gets here: rcl ends the
        process with exit code 102 as rclpy is imported.)"""
        self._context = Context()
        try:
            rclpy.init(
                args=_ROS_ARGS,
                context=self._context,
                domain_id=self.config.domain_id,
                signal_handler_options=SignalHandlerOptions.NO,
            )
            self._node = Node(
                self.config.node_name,
                context=self._context,
                enable_rosout=False,
                start_parameter_services=False,
            )
        except Exception as exc:  # rclpy raises its own RCLError and friends
            self._context.try_shutdown()
            raise Ros2Unavailable(
                f"ROS 2 did not start the bridge's node: {exc} (RMW_IMPLEMENTATION and the "
                f"ROS 2 install: {INSTALL_HINT})"
            ) from None
        self._executor = SingleThreadedExecutor(context=self._context)
        self._executor.add_node(self._node)
        self._wake = self._node.create_guard_condition(lambda: None)
        self._stopping = threading.Event()
        self._spinner = threading.Thread(target=self._spin, name="arpz-ros2-rclpy", daemon=True)
        self._spinner.start()

    def _spin(self) -> None:
        while not self._stopping.is_set() and self._context.ok():
            try:
                self._executor.spin_once(timeout_sec=_SPIN_S)
            except _NoAnswer:
                pass  # counted and logged by the bridge already
            except ExternalShutdownException:
                return
            except Exception:  # a bug must not stop the node: loud once per cause
                throttled.exception("rclpy spin", "ROS 2 bridge: rclpy's executor raised")

    def _close_node(self) -> None:
        if not hasattr(self, "_spinner"):
            return  # never started
        self._stopping.set()
        self._spinner.join(timeout=5.0)
        self._executor.shutdown(timeout_sec=1.0)
        self._node.destroy_node()
        self._context.try_shutdown()

    # -- the entities ----------------------------------------------------------------------------

    def _topic_qos(self, profile: Any) -> rmw_zenoh.RmwQos:
        return rmw_zenoh.qos_from_profile(profile, transient_local=True)

    def _declare_publisher(
        self, name: str, ros_type: str, qos: rmw_zenoh.RmwQos, robot: str
    ) -> TopicPort:
        cls = interface_class(ros_type)
        events = PublisherEventCallbacks(
            incompatible_qos=lambda info: self._on_incompatible_qos(
                "publisher", name, _policy(info)
            )
        )
        publisher = self._node.create_publisher(cls, name, rclpy_qos(qos), event_callbacks=events)
        return _RclpyTopic(self._node, publisher)

    def _command_qos(self, profile: Any) -> rmw_zenoh.RmwQos:
        return command_qos(profile)

    def _declare_subscription(
        self, name: str, mapping: Ros2CommandConfig, index: int, qos: rmw_zenoh.RmwQos, robot: str
    ) -> Port:
        cls = interface_class(mapping.type)
        events = SubscriptionEventCallbacks(
            incompatible_qos=lambda info: self._on_incompatible_qos(
                "subscription", name, _policy(info)
            )
        )

        def on_message(cdr: bytes) -> None:
            self._on_ros_command(index, robot, name, cdr)

        subscription = self._node.create_subscription(
            cls, name, on_message, rclpy_qos(qos), event_callbacks=events, raw=True
        )
        return _RclpyEntity(lambda: self._node.destroy_subscription(subscription))

    def _declare_service(self, name: str, service_type: str, robot: str, service: str) -> Port:
        cls = interface_class(service_type)
        server = self._node.create_service(
            cls,
            name,
            self._serve(robot, service, name, cls),
            qos_profile=qos_profile_services_default,
        )
        return _RclpyEntity(lambda: self._node.destroy_service(server))

    def _serve(
        self, robot: str, service: str, name: str, cls: Any
    ) -> Callable[[Any, Any], Coroutine[None, None, Any]]:
        async def serve(request: Any, response: Any) -> Any:
            answer = _Answer(self._wake)
            self._on_ros_service(robot, service, name, serialize_message(request), answer.set)
            cdr = await answer
            if cdr is None:
                raise _NoAnswer(name)
            return deserialize_message(cdr, cls.Response)

        return serve
