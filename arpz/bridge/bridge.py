"""The running bridge: the fleet's sensor topics out to ROS 2, ROS 2 commands and service calls in
to the robots.

``Bridge`` is one ROS 2 node (``[ros2] node_name``). This module holds the part every backend
shares (the fleet side, the conversions, the worker, the counters) and the rmw_zenoh backend,
which speaks rmw_zenoh's protocol on a Zenoh session: inside the CEDDP the CEDDP's own router
session, standalone (``python -m arpz.bridge``) a client session. The rclpy backend
(``arpz.bridge.rclpy_backend``, ``[ros2] backend = "rclpy"``) subclasses it and overrides the
``_declare_*`` hooks and the start and close of its node (docs/ros2.md "Backends");
``arpz.bridge.factory.make_bridge`` picks the backend from the config.

Fleet -> ROS 2. It learns every robot's topics from the robots' announcements (as the CEDDP
does), reads their samples through the reliable channel (one wildcard ``Reader`` for the small
sensors, one ``FrameReader`` for camera frames and point clouds), converts each reading to its
standard ROS 2 message (arpz.core.rosmsg) and hands the CDR to the topic's publisher: for
rmw_zenoh the topic's key with rmw_zenoh's attachment and a liveliness token carrying the
topic's QoS mapped from the arpz profile, so ``ros2 topic list`` shows it.

ROS 2 -> fleet. For each ``[[ros2.commands]]`` mapping, one subscription per robot that acts on
the mapped command (rmw_zenoh: one Zenoh subscriber on every robot's command topic, a wildcard,
and a subscription token per robot); each message becomes an arpz ``Command`` written through a
reliable channel writer on the robot's ``cmd/{command}`` key with the fleet's command QoS: the
robot's reader, its lifespan check and its command watchdog treat it as any command.

Services. Each service a robot announces is a ROS 2 service ``/{robot}/{name}`` of its type
(rmw_zenoh: a queryable on the service's key and an SS token), when the bridge has a
``ServiceCalls`` (the CEDDP's ``ServiceCaller``): a request's CDR becomes the request message,
called through it, and the response goes back as CDR when its future completes.

Every callback only queues; one worker (``arpz-ros2``) does the work in arrival order, so the
maps of topics and robots have one owner. Bad input (an undecodable sample, a reading with no
ROS 2 message, a command of another type, a CDR that does not decode, a topic nobody maps) is
counted and logged once per topic and cause (arpz.core.throttled_log), never raised.
"""

from __future__ import annotations

import concurrent.futures
import functools
import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any, Protocol

import msgspec

from arpz.bridge import naming, rmw_zenoh
from arpz.bridge.commands import command_value
from arpz.bridge.type_hash import UnknownTypeError, service_type_hash, type_hash
from arpz.channel import FrameInfo, FrameReader, MessageLostStatus, ReaderEventCallbacks
from arpz.channel.io import Inlet, Outlet
from arpz.core import keys
from arpz.core.config import (
    LARGE_KINDS,
    LARGE_SAMPLE_BYTES,
    LARGE_TYPES,
    Ros2CommandConfig,
    Ros2Config,
    TrafficQos,
)
from arpz.core.messages import (
    ANNOUNCE_DECODER,
    DECODE_ERRORS,
    LARGE_SAMPLE_DECODER,
    MESSAGE_SAMPLE_DECODER,
    SAMPLE_DECODER,
    Command,
    MessageCommand,
    encode,
    new_incarnation,
    writer_id,
)
from arpz.core.msgtypes import MessageTypeError, MessageTypes
from arpz.core.rosmsg.convert import ConversionError, deserialize, to_cdr
from arpz.core.rosmsg.types import UnknownKindError, ros_type_for
from arpz.core.throttled_log import ThrottledLog
from arpz.core.transport import DeferredQueries, Handle, Publisher, Responder, Transport

log = logging.getLogger(__name__)
#: bad input: one line per topic and cause per 10 s
throttled = ThrottledLog(log)

_ANNOUNCE, _PRESENCE, _SAMPLE, _FRAME, _COMMAND, _ROS_COMMAND, _SERVICE, _STOP = range(8)
#: how long a reader's thread waits for room in the worker's queue before the item is dropped
#: (and counted): the readers' own flow control holds the robots meanwhile
_PUT_TIMEOUT_S = 1.0


#: how long a bridged service call may take at the robot, s (ServiceCaller's default)
SERVICE_TIMEOUT_S = 5.0


class ServiceCalls(Protocol):
    """What the bridge needs to call a robot's service: ``arpz.ceddp.services.ServiceCaller``
    (the CEDDP passes its own; the bridge's layer may not import the CEDDP's)."""

    def call_async(
        self,
        robot: str,
        name: str,
        request: object,
        timeout_s: float = ...,
        *,
        type: str | None = None,
    ) -> concurrent.futures.Future[msgspec.Struct]: ...


class Port(Protocol):
    """One ROS 2 entity of a backend (a publisher, a subscription, a service server)."""

    def close(self) -> None: ...


class TopicPort(Port, Protocol):
    """A backend's publisher of one bridged topic: ``put`` one message's CDR."""

    def put(self, cdr: bytes, seq: int, stamp_ns: int) -> None: ...


#: a service call's answer: the response's CDR, or None for no response
Answer = Callable[[bytes | None], None]


@dataclass
class BridgeCounters:
    """What the bridge did, for its stats and the CEDDP's summary (``ros2``)."""

    #: arpz samples and frames taken from the channel
    samples_in: int = 0
    #: ROS 2 messages published (one per sample converted)
    published: int = 0
    #: samples whose arpz payload did not decode
    undecodable_samples: int = 0
    #: readings with no ROS 2 message (e.g. a float32 out of range, a frame of odd size)
    conversion_errors: int = 0
    #: a sensor kind with no ROS 2 type, or a message of another type on a command topic
    unknown_type: int = 0
    #: samples of a topic no announcement mapped yet, commands for a robot that does not act on
    #: the mapped command (or no robot of that name)
    unmapped: int = 0
    #: ROS 2 command messages received, and written to a robot's command key
    commands_in: int = 0
    commands_sent: int = 0
    #: commands written while the robot's reader was not matched (they reached no one)
    commands_unmatched: int = 0
    commands_write_failures: int = 0
    #: command payloads that are not CDR of the mapped type
    bad_cdr: int = 0
    #: commands or service requests without rmw_zenoh's 33-byte attachment (a command is still
    #: accepted: the attachment is metadata; a request is not answered: its reply needs it)
    bad_attachment: int = 0
    #: items the worker's queue refused after waiting (queue_limit)
    queue_dropped: int = 0
    #: sensor samples the reliable channel reported lost before the bridge
    channel_lost: int = 0
    #: ROS 2 service calls taken, answered with the robot's response, and not (the robot's
    #: call failed: answered by a failure response or not at all, docs/ros2.md "Services")
    service_calls: int = 0
    service_answered: int = 0
    service_failed: int = 0
    #: ROS 2 endpoints whose QoS cannot match one of the bridge's (the rclpy backend: the RMW's
    #: own incompatible-QoS events on the bridge's publishers and subscriptions)
    qos_incompatible: int = 0


@dataclass
class _TopicOut:
    """One bridged sensor topic: a ROS 2 publisher of the node."""

    robot: str
    topic: str
    kind: str
    #: the ROS 2 topic, its type and the QoS it offers
    name: str
    ros_type: str
    qos: rmw_zenoh.RmwQos
    port: TopicPort
    frame_id: str
    seq: int = 0
    conversion_errors: int = 0
    #: a typed topic's ROS 2 type (its samples are decoded and written as CDR of it)
    msg_type: str | None = None


@dataclass
class _CommandIn:
    """One robot's command topic: a ROS 2 subscription of the node."""

    robot: str
    mapping: Ros2CommandConfig
    name: str
    port: Port
    outlet: Outlet
    received: int = 0
    sent: int = 0
    seq: int = 0


@dataclass
class _ServiceIn:
    """One robot's service: a ROS 2 service server of the node."""

    robot: str
    service: str
    service_type: str
    name: str
    port: Port
    calls: int = 0
    answered: int = 0
    failed: int = 0


@dataclass
class _Robot:
    topics: dict[str, _TopicOut] = field(default_factory=dict)
    commands: dict[str, _CommandIn] = field(default_factory=dict)
    services: dict[str, _ServiceIn] = field(default_factory=dict)
    #: the commands the robot takes as messages: name -> ROS 2 type (its announcement's)
    command_types: dict[str, str] = field(default_factory=dict)


@dataclass
class _Handles:
    """A backend's entity made of Zenoh declarations: closed by undeclaring them."""

    handles: list[Any]

    def close(self) -> None:
        for handle in self.handles:
            handle.undeclare()


@dataclass
class _ZenohTopic(_Handles):
    """An rmw_zenoh publisher: its key's publisher and its token."""

    publisher: Publisher
    gid: bytes

    def put(self, cdr: bytes, seq: int, stamp_ns: int) -> None:
        self.publisher.put(cdr, attachment=rmw_zenoh.attachment(seq, stamp_ns, self.gid))


class Bridge:
    """Thread: ``start`` opens everything and starts the worker; ``close`` undeclares it all.
    ``stats`` may be called from any thread. The rmw_zenoh backend."""

    backend = "rmw_zenoh"

    def __init__(
        self,
        transport: Transport,
        fleet: str,
        traffic: TrafficQos,
        config: Ros2Config,
        *,
        partition: str = "*",
        zid: str | None = None,
        types: MessageTypes | None = None,
        services: ServiceCalls | None = None,
    ) -> None:
        """``types``: the message types of the fleet's typed topics (the standard ones and the
        fleet's ``msg_paths``); a typed topic of a type it does not know is not bridged.
        ``services``: what calls the robots' services (None: they are not bridged)."""
        self.transport = transport
        self.types = types or MessageTypes()
        self.fleet = fleet
        self.traffic = traffic
        self.config = config
        self.partition = partition
        self.services = services
        #: rmw_zenoh names the session in every token; any unique hex string will do for a fake
        self.zid = zid or str(getattr(transport, "zid", "")) or new_incarnation()
        self.writer = writer_id("ros2-bridge", new_incarnation())
        self.counters = BridgeCounters()
        self._lock = threading.Lock()
        #: (what, key, payload, extra): extra is (attachment, mapping index) for a command
        self._queue: queue.Queue[tuple[int, str, bytes, Any]] = queue.Queue(config.queue_limit)
        self._robots: dict[str, _Robot] = {}
        #: ROS 2 command topic -> (robot, mapping index), for the robots acting on a mapping
        self._command_topics: dict[tuple[int, str], str] = {}
        self._next_id = 1
        #: ROS 2 topic -> counts of its closed incarnations (a robot that left)
        self._retired_topics: dict[str, dict[str, Any]] = {}
        self._retired_commands: dict[str, dict[str, Any]] = {}
        self._retired_services: dict[str, dict[str, Any]] = {}
        self._handles: list[Handle] = []
        self._inlets: list[Inlet] = []
        self._frames: FrameReader | None = None
        self._worker = threading.Thread(target=self._run, name="arpz-ros2", daemon=True)
        self._hashes = {m.type: self._hash(m.type) for m in config.commands}
        self._no_services_logged = False
        self.node = rmw_zenoh.Entity(
            domain_id=config.domain_id,
            zid=self.zid,
            node_id="0",
            entity_id="0",
            kind=rmw_zenoh.NODE,
            namespace="/",
            node=config.node_name,
        )

    # -- life cycle ------------------------------------------------------------------------------

    def start(self) -> None:
        t, fleet = self.transport, self.fleet
        self._start_node()
        self._worker.start()
        self._inlets.append(
            Inlet(t, keys.all_announce(fleet), self.traffic.profile("report"), self._on_announce)
        )
        self._handles.append(t.watch_liveliness(keys.all_presence(fleet), self._on_presence))
        self._inlets.append(
            Inlet(
                t,
                keys.all_sensors(fleet, self.partition),
                self.traffic.profile("sensor"),
                lambda key, payload: self._put(_SAMPLE, key, payload),
                on_lost=self._on_lost,
            )
        )
        frames_qos = self.traffic.profile("frames")
        if frames_qos is not None:
            self._frames = FrameReader(
                t,
                keys.all_frames(fleet, self.partition),
                frames_qos,
                self._on_frame,
                max_frame_bytes=LARGE_SAMPLE_BYTES,
                events=ReaderEventCallbacks(message_lost=self._on_lost),
            )
        log.info(
            "ROS 2 bridge: node /%s on domain %d (%s), fleet '%s'",
            self.config.node_name,
            self.config.domain_id,
            self.backend,
            fleet,
        )

    def close(self) -> None:
        """Stop reading, let the worker finish what is queued (bounded), undeclare everything."""
        for inlet in self._inlets:
            inlet.close()
        if self._frames is not None:
            self._frames.close()
        for handle in self._handles:
            handle.undeclare()
        if self._worker.is_alive():
            self._queue.put((_STOP, "", b"", None))
            self._worker.join(timeout=5.0)
        for robot in list(self._robots):
            self._drop_robot(robot)
        self._close_node()

    def __enter__(self) -> Bridge:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the backend: rmw_zenoh (the rclpy backend overrides these) -------------------------------

    def _start_node(self) -> None:
        """The node's token, and one Zenoh subscriber per command mapping (every robot's)."""
        self._handles.append(self.transport.declare_token(self.node.token()))
        for index, mapping in enumerate(self.config.commands):
            expr = naming.command_key_expr(self.config.domain_id, mapping.topic)
            self._handles.append(
                self.transport.subscribe(expr, functools.partial(self._on_command, index))
            )

    def _close_node(self) -> None:
        """Nothing more: the node's token went with the handles."""

    def _topic_qos(self, profile: Any) -> rmw_zenoh.RmwQos:
        return rmw_zenoh.qos_from_profile(profile)

    def _declare_publisher(
        self, name: str, ros_type: str, qos: rmw_zenoh.RmwQos, robot: str
    ) -> TopicPort:
        entity = self._new_entity(rmw_zenoh.PUBLISHER, name, ros_type, qos)
        # as rmw_zenoh: congestion control BLOCK only for RELIABLE + KEEP_ALL, else DROP
        block = qos.reliability == rmw_zenoh.RELIABLE and qos.history == rmw_zenoh.KEEP_ALL
        publisher = self.transport.publisher(entity.data_key, block=block)
        token = self.transport.declare_token(entity.token())
        return _ZenohTopic([token, publisher], publisher, entity.gid)

    def _command_qos(self, profile: Any) -> rmw_zenoh.RmwQos:
        return rmw_zenoh.qos_from_profile(profile)

    def _declare_subscription(
        self, name: str, mapping: Ros2CommandConfig, index: int, qos: rmw_zenoh.RmwQos, robot: str
    ) -> Port:
        """A subscription token: the mapping's wildcard subscriber takes the messages."""
        entity = self._new_entity(rmw_zenoh.SUBSCRIPTION, name, mapping.type, qos)
        return _Handles([self.transport.declare_token(entity.token())])

    def _declare_service(self, name: str, service_type: str, robot: str, service: str) -> Port:
        """A queryable on the service's key (complete, as rmw_zenoh declares a service's) and an
        SS token: rmw_zenoh's clients find it in the graph and query its key."""
        entity = self._new_entity(
            rmw_zenoh.SERVICE,
            name,
            service_type,
            rmw_zenoh.SERVICE_QOS,
            type_hash=service_type_hash(service_type, self.types),
        )
        if not isinstance(self.transport, DeferredQueries):
            raise UnknownTypeError(
                f"{self.transport.__class__.__name__} has no deferred queries: no services"
            )
        queryable = self.transport.serve_deferred(
            entity.data_key, functools.partial(self._on_service_query, robot, service)
        )
        return _Handles([self.transport.declare_token(entity.token()), queryable])

    def _on_service_query(
        self, robot: str, service: str, key: str, payload: bytes, responder: Responder
    ) -> None:
        """From Zenoh's thread: queue it; a full queue finishes the query unanswered."""
        run = functools.partial(self._zenoh_call, robot, service, key, responder)
        if not self._offer(_SERVICE, key, payload, run):
            responder.finish()

    def _zenoh_call(
        self, robot: str, service: str, key: str, responder: Responder, payload: bytes
    ) -> None:
        """rmw_zenoh's request header is the query's attachment: its sequence number and client
        GID go back in the reply's, which is how the client matches the response to its call."""
        try:
            header = rmw_zenoh.parse_attachment(responder.attachment or b"")
        except rmw_zenoh.WireError as exc:
            self._bad("bad_attachment", f"service attachment {key}", "%s: %s", key, exc)
            responder.finish()
            return

        def answer(cdr: bytes | None) -> None:
            if cdr is not None:
                reply = rmw_zenoh.attachment(header.sequence_number, time.time_ns(), header.gid)
                responder.reply(cdr, attachment=reply)
            responder.finish()

        self._call(robot, service, answer, payload)

    def _new_entity(
        self,
        kind: str,
        topic: str,
        ros_type: str,
        qos: rmw_zenoh.RmwQos,
        *,
        type_hash: str | None = None,
    ) -> rmw_zenoh.Entity:
        entity_id, self._next_id = self._next_id, self._next_id + 1
        return rmw_zenoh.Entity(
            domain_id=self.config.domain_id,
            zid=self.zid,
            node_id=self.node.node_id,
            entity_id=str(entity_id),
            kind=kind,
            namespace=self.node.namespace,
            node=self.node.node,
            topic=topic,
            ros_type=ros_type,
            type_hash=type_hash or self._hash(ros_type),
            qos=qos,
        )

    # -- callbacks: only queue ---------------------------------------------------------------------

    def _put(self, kind: int, key: str, payload: bytes) -> None:
        """From a reader's own thread: wait for room (the channel holds the robots meanwhile)."""
        try:
            self._queue.put((kind, key, payload, None), timeout=_PUT_TIMEOUT_S)
        except queue.Full:
            self._dropped(key)

    def _offer(self, kind: int, key: str, payload: bytes, extra: Any) -> bool:
        """From Zenoh's (or the ROS 2 executor's) thread: never block it. False: dropped."""
        try:
            self._queue.put_nowait((kind, key, payload, extra))
        except queue.Full:
            self._dropped(key)
            return False
        return True

    def _dropped(self, key: str) -> None:
        with self._lock:
            self.counters.queue_dropped += 1
        throttled.warning(
            "ros2 queue full", "ROS 2 bridge: queue full (queue_limit): %s dropped", key
        )

    def _on_command(self, index: int, key: str, payload: bytes, att: bytes | None) -> None:
        self._offer(_COMMAND, key, payload, (att, index))

    def _on_announce(self, key: str, payload: bytes) -> None:
        self._put(_ANNOUNCE, key, payload)

    def _on_presence(self, key: str, alive: bool) -> None:
        self._offer(_PRESENCE, key, b"\x01" if alive else b"", None)

    def _on_frame(self, payload: bytes, info: FrameInfo) -> None:
        self._put(_FRAME, info.key, payload)

    def _on_lost(self, status: MessageLostStatus) -> None:
        with self._lock:
            self.counters.channel_lost += status.total_count_change

    def _on_ros_command(self, index: int, robot: str, topic: str, payload: bytes) -> None:
        """A backend's command message (its CDR) for ``robot`` (from the backend's thread)."""
        self._offer(_ROS_COMMAND, topic, payload, (index, robot))

    def _on_ros_service(
        self, robot: str, service: str, name: str, payload: bytes, answer: Answer
    ) -> None:
        """A backend's service request (its CDR): ``answer`` gets the response's CDR or None
        (from the worker, or the transport's thread when the call completes)."""
        run = functools.partial(self._call, robot, service, answer)
        if not self._offer(_SERVICE, name, payload, run):
            answer(None)

    def _on_incompatible_qos(self, role: str, name: str, policy: str) -> None:
        """A backend's incompatible-QoS event (from its own thread)."""
        self._bad(
            "qos_incompatible",
            f"qos {role} {name} {policy}",
            "%s %s: a ROS 2 endpoint's QoS cannot match it (policy %s)",
            role,
            name,
            policy,
        )

    # -- the worker ------------------------------------------------------------------------------

    def _run(self) -> None:
        while True:
            kind, key, payload, extra = self._queue.get()
            if kind == _STOP:
                return
            try:
                if kind in (_SAMPLE, _FRAME):
                    self._publish(key, payload, large=kind == _FRAME)
                elif kind == _COMMAND:
                    attachment, index = extra
                    self._command(index, key, payload, attachment)
                elif kind == _ROS_COMMAND:
                    index, robot = extra
                    self._apply_command(index, robot, key, payload)
                elif kind == _SERVICE:  # extra: what takes the request (its backend's)
                    extra(payload)
                elif kind == _ANNOUNCE:
                    self._announce(key, payload)
                elif kind == _PRESENCE and not payload:
                    parsed = keys.parse_robot_key(key)
                    if parsed is not None:
                        self._drop_robot(parsed[0])
            except Exception:  # a bug must not stop the bridge: loud once per cause, counted
                throttled.exception(f"ros2 worker {kind}", "ROS 2 bridge failed on %s", key)

    def _bad(self, counter: str, cause: str, message: str, *args: object) -> None:
        with self._lock:
            setattr(self.counters, counter, getattr(self.counters, counter) + 1)
        throttled.warning(cause, "ROS 2 bridge: " + message, *args)

    def _hash(self, ros_type: str) -> str:
        """The type's RIHS01: from the standard definitions, else from the fleet's own."""
        try:
            return type_hash(ros_type)
        except UnknownTypeError:
            return self.types.type_hash(ros_type)

    def _announce(self, key: str, payload: bytes) -> None:
        """A robot's topics, commands and services: a publisher for each new sensor topic, a
        subscription for each command it acts on that a mapping names, a service server for
        each service."""
        try:
            announce = ANNOUNCE_DECODER.decode(payload)
        except DECODE_ERRORS as exc:
            self._bad(
                "undecodable_samples",
                f"announce {key}",
                "undecodable announcement %s: %s",
                key,
                exc,
            )
            return
        robot = announce.robot
        parsed = keys.parse_robot_key(key)
        if parsed is None or parsed[0] != robot:
            self._bad("unmapped", f"announce {key}", "announcement of %r on %s refused", robot, key)
            return
        state = self._robots.setdefault(robot, _Robot())
        state.command_types = dict(announce.command_types)
        for info in announce.sensors:
            if info.topic not in state.topics:
                self._open_topic(state, robot, info.topic, info.kind, info.msg_type or None)
        for index, mapping in enumerate(self.config.commands):
            if mapping.command in announce.commands and mapping.command not in state.commands:
                self._open_command(state, robot, index, mapping)
        for service, service_type in announce.services.items():
            if service not in state.services:
                self._open_service(state, robot, service, service_type)

    def _open_topic(
        self, state: _Robot, robot: str, topic: str, kind: str, msg_type: str | None = None
    ) -> None:
        name = naming.topic_name(self.config, robot, topic, kind)
        try:
            if msg_type is not None:
                self.types.require(msg_type)
                ros_type = msg_type
            else:
                ros_type = ros_type_for(kind)
            self._hash(ros_type)
            large = kind in LARGE_KINDS or msg_type in LARGE_TYPES
            qos = self._topic_qos(self.traffic.profile("frames" if large else "sensor"))
            port = self._declare_publisher(name, ros_type, qos, robot)
        except (UnknownKindError, UnknownTypeError, MessageTypeError) as exc:
            self._bad(
                "unknown_type", f"type {robot}/{topic}", "%s/%s not bridged: %s", robot, topic, exc
            )
            return
        state.topics[topic] = _TopicOut(
            robot,
            topic,
            kind,
            name,
            ros_type,
            qos,
            port,
            naming.frame_id(robot, topic),
            msg_type=msg_type,
        )
        log.info("ROS 2 bridge: %s/%s -> %s [%s]", robot, topic, name, ros_type)

    def _open_command(
        self, state: _Robot, robot: str, index: int, mapping: Ros2CommandConfig
    ) -> None:
        name = naming.fill(mapping.topic, robot)
        profile = self.traffic.profile("command", downlink=True)
        try:
            port = self._declare_subscription(
                name, mapping, index, self._command_qos(profile), robot
            )
        except UnknownTypeError as exc:
            self._bad("unknown_type", f"command type {name}", "%s not bridged: %s", name, exc)
            return
        outlet = Outlet(
            self.transport, keys.command_key(self.fleet, robot, mapping.command), profile
        )
        state.commands[mapping.command] = _CommandIn(robot, mapping, name, port, outlet)
        with self._lock:
            self._command_topics[(index, name)] = robot
        log.info("ROS 2 bridge: %s [%s] -> %s cmd/%s", name, mapping.type, robot, mapping.command)

    def _open_service(self, state: _Robot, robot: str, service: str, service_type: str) -> None:
        if self.services is None:
            if not self._no_services_logged:
                self._no_services_logged = True
                log.info(
                    "ROS 2 bridge: robots' services are not bridged (no service caller: the "
                    "bridge runs inside the CEDDP for them)"
                )
            return
        name = naming.service_name(robot, service)
        try:
            self.types.service_types(service_type)
            port = self._declare_service(name, service_type, robot, service)
        except (UnknownTypeError, MessageTypeError) as exc:
            self._bad("unknown_type", f"service {name}", "%s not bridged: %s", name, exc)
            return
        state.services[service] = _ServiceIn(robot, service, service_type, name, port)
        log.info("ROS 2 bridge: service %s [%s] -> %s/%s", name, service_type, robot, service)

    def _drop_robot(self, robot: str) -> None:
        """The robot left: its publishers, tokens and command writers go (it announces again)."""
        state = self._robots.pop(robot, None)
        if state is None:
            return
        for out in state.topics.values():
            out.port.close()
            self._retire(out)
        with self._lock:
            for key in [k for k, r in self._command_topics.items() if r == robot]:
                del self._command_topics[key]
        for command in state.commands.values():
            command.port.close()
            command.outlet.close(0.0)
            self._retire(command)
        for service in state.services.values():
            service.port.close()
            self._retire(service)

    def _publish(self, key: str, payload: bytes, *, large: bool) -> None:
        with self._lock:
            self.counters.samples_in += 1
        parsed = keys.parse_robot_key(key)
        state = self._robots.get(parsed[0]) if parsed is not None else None
        out = state.topics.get(parsed[2]) if state is not None and parsed is not None else None
        if out is None:
            self._bad("unmapped", f"unmapped {key}", "%s: no announced topic, not bridged", key)
            return
        if out.msg_type is not None:
            self._publish_typed(out, key, payload, large=large)
            return
        decoder = LARGE_SAMPLE_DECODER if large or out.kind in LARGE_KINDS else SAMPLE_DECODER
        try:
            sample = decoder.decode(payload)
        except DECODE_ERRORS as exc:
            self._bad("undecodable_samples", f"undecodable {key}", "%s: undecodable: %s", key, exc)
            return
        try:
            cdr = to_cdr(out.kind, sample.value, stamp_ns=sample.stamp_ns, frame_id=out.frame_id)
        except ConversionError as exc:
            out.conversion_errors += 1
            self._bad("conversion_errors", f"convert {key}", "%s: %s", key, exc)
            return
        out.seq += 1
        out.port.put(cdr, out.seq, sample.stamp_ns)
        with self._lock:
            self.counters.published += 1

    def _publish_typed(self, out: _TopicOut, key: str, payload: bytes, *, large: bool) -> None:
        """A typed topic's message as CDR of its own type (the robot's header kept)."""
        assert out.msg_type is not None
        try:
            large = large or out.msg_type in LARGE_TYPES
            sample = (LARGE_SAMPLE_DECODER if large else MESSAGE_SAMPLE_DECODER).decode(payload)
            message = self.types.decode(out.msg_type, sample.value)
        except DECODE_ERRORS as exc:
            self._bad("undecodable_samples", f"undecodable {key}", "%s: undecodable: %s", key, exc)
            return
        cdr = self.types.to_cdr(out.msg_type, message)
        out.seq += 1
        out.port.put(cdr, out.seq, sample.stamp_ns)
        with self._lock:
            self.counters.published += 1

    def _command(self, index: int, key: str, payload: bytes, attachment: bytes | None) -> None:
        """An rmw_zenoh command sample: its key names the topic and the type."""
        mapping = self.config.commands[index]
        parsed = rmw_zenoh.parse_topic_key(key)
        if parsed is None or (parsed.ros_type, parsed.type_hash) != (
            mapping.type,
            self._hashes[mapping.type],
        ):
            with self._lock:
                self.counters.commands_in += 1
            self._bad(
                "unknown_type",
                f"command type {key}",
                "%s: not %s (%s): refused",
                key,
                mapping.type,
                self._hashes[mapping.type],
            )
            return
        with self._lock:
            robot = self._command_topics.get((index, parsed.topic))
        if robot is not None and (
            attachment is None or len(attachment) != rmw_zenoh.ATTACHMENT_BYTES
        ):
            self._bad(
                "bad_attachment",
                f"attachment {parsed.topic}",
                "%s: no rmw_zenoh attachment",
                parsed.topic,
            )
        self._apply_command(index, robot, parsed.topic, payload)

    def _apply_command(self, index: int, robot: str | None, topic: str, payload: bytes) -> None:
        """One ROS 2 command message (CDR of the mapping's type) on ``topic``, for ``robot``:
        written to the robot's command key."""
        mapping = self.config.commands[index]
        with self._lock:
            self.counters.commands_in += 1
        state = self._robots.get(robot) if robot is not None else None
        command = state.commands.get(mapping.command) if state is not None else None
        if state is None or command is None:
            self._bad(
                "unmapped",
                f"command topic {topic}",
                "%s: no robot acting on '%s' has this topic: refused",
                topic,
                mapping.command,
            )
            return
        takes = state.command_types.get(mapping.command)
        try:
            if takes is not None:  # the robot takes the message itself: passed through
                if takes != mapping.type:
                    raise ValueError(f"robot {robot} takes {mapping.command} as {takes}")
                raw = msgspec.Raw(self.types.encode(self.types.from_cdr(takes, payload)))
            else:
                value = command_value(mapping.type, deserialize(payload, mapping.type))
        except (ConversionError, AttributeError, TypeError, ValueError, KeyError) as exc:
            self._bad("bad_cdr", f"cdr {topic}", "%s: %s", topic, exc)
            return
        command.received += 1
        command.seq += 1
        stamp = time.time_ns()
        message: msgspec.Struct = (
            MessageCommand(self.writer, command.seq, stamp, raw)
            if takes is not None
            else Command(writer=self.writer, seq=command.seq, stamp_ns=stamp, value=value)
        )
        before = command.outlet.unmatched
        ok = command.outlet.send(encode(message), stamp, count_unmatched=True)
        with self._lock:
            self.counters.commands_unmatched += command.outlet.unmatched - before
            if ok:
                command.sent += 1
                self.counters.commands_sent += 1
            else:
                self.counters.commands_write_failures += 1

    # -- services --------------------------------------------------------------------------------

    def _call(self, robot: str, service: str, answer: Answer, payload: bytes) -> None:
        """Call ``robot``'s ``service`` with the request's CDR; ``answer`` gets the response's
        CDR when the call completes (on the transport's thread), or None / a failure response
        (``failure_response``) when it fails."""
        with self._lock:
            self.counters.service_calls += 1
        state = self._robots.get(robot)
        entry = state.services.get(service) if state is not None else None
        if entry is None or self.services is None:
            self._service_failed(None, answer, None, f"{robot}/{service}: not served any more")
            return
        entry.calls += 1
        request_type, response_type = self.types.service_types(entry.service_type)
        try:
            request = self.types.from_cdr(request_type, payload)
        except (ConversionError, AttributeError, TypeError, ValueError, KeyError) as exc:
            self._bad("bad_cdr", f"cdr {entry.name}", "%s: request: %s", entry.name, exc)
            self._service_failed(entry, answer, response_type, f"bad request: {exc}")
            return
        future = self.services.call_async(
            robot, service, request, SERVICE_TIMEOUT_S, type=entry.service_type
        )

        def done(call: concurrent.futures.Future[msgspec.Struct]) -> None:
            try:
                response = call.result()
            except Exception as exc:  # a ServiceError: timeout, gone, the handler failed...
                self._service_failed(entry, answer, response_type, str(exc))
                return
            try:
                cdr = self.types.to_cdr(response_type, response)
            except Exception as exc:
                self._service_failed(entry, answer, response_type, f"response: {exc}")
                return
            with self._lock:
                entry.answered += 1
                self.counters.service_answered += 1
            answer(cdr)

        future.add_done_callback(done)

    def _service_failed(
        self, entry: _ServiceIn | None, answer: Answer, response_type: str | None, error: str
    ) -> None:
        with self._lock:
            self.counters.service_failed += 1
            if entry is not None:
                entry.failed += 1
        name = entry.name if entry is not None else "service"
        throttled.warning(f"service {name} {error}", "ROS 2 bridge: %s: %s", name, error)
        response = (
            failure_response(self.types, response_type, error)
            if response_type is not None
            else None
        )
        if response_type is None or response is None:
            answer(None)
        else:
            answer(self.types.to_cdr(response_type, response))

    # -- stats -----------------------------------------------------------------------------------

    def _row(self, item: _TopicOut | _CommandIn | _ServiceIn) -> dict[str, Any]:
        if isinstance(item, _TopicOut):
            return {
                "robot": item.robot,
                "topic": item.topic,
                "type": item.ros_type,
                "published": item.seq,
                "conversion_errors": item.conversion_errors,
                "qos": item.qos.describe(),
            }
        if isinstance(item, _ServiceIn):
            return {
                "robot": item.robot,
                "service": item.service,
                "type": item.service_type,
                "calls": item.calls,
                "answered": item.answered,
                "failed": item.failed,
            }
        return {
            "robot": item.robot,
            "command": item.mapping.command,
            "type": item.mapping.type,
            "received": item.received,
            "sent": item.sent,
        }

    def _table(self, item: _TopicOut | _CommandIn | _ServiceIn) -> dict[str, dict[str, Any]]:
        if isinstance(item, _TopicOut):
            return self._retired_topics
        return self._retired_services if isinstance(item, _ServiceIn) else self._retired_commands

    def _retire(self, item: _TopicOut | _CommandIn | _ServiceIn) -> None:
        """Keep a closed topic's counts for the stats (added to a later incarnation's)."""
        table = self._table(item)
        row = self._row(item)
        with self._lock:
            table[item.name] = _merged(table.get(item.name), row)

    def stats(self) -> dict[str, Any]:
        """The bridge's counters, its topics, command topics and services (live and closed),
        and the sensor channel's view."""
        robots = dict(self._robots)  # the worker may add entries meanwhile: copy, then read
        live: list[_TopicOut | _CommandIn | _ServiceIn] = []
        for state in robots.values():
            live += list(state.topics.values())
            live += list(state.commands.values())
            live += list(state.services.values())
        with self._lock:
            counters = asdict(self.counters)
            tables = {
                id(self._retired_topics): dict(self._retired_topics),
                id(self._retired_commands): dict(self._retired_commands),
                id(self._retired_services): dict(self._retired_services),
            }
        for item in live:
            table = tables[id(self._table(item))]
            table[item.name] = _merged(table.get(item.name), self._row(item))
        channel = self._inlets[1].stats() if len(self._inlets) > 1 else None
        return {
            "node": f"/{self.config.node_name}",
            "domain_id": self.config.domain_id,
            "backend": self.backend,
            "counters": counters,
            "topics": tables[id(self._retired_topics)],
            "commands": tables[id(self._retired_commands)],
            "services": tables[id(self._retired_services)],
            "channel": msgspec.to_builtins(channel) if channel is not None else None,
        }


def failure_response(types: MessageTypes, response_type: str, error: str) -> Any:
    """The response a failed call gets when its type follows std_srvs' convention, exactly
    ``bool success`` and ``string message`` (``Trigger``, ``SetBool``): success False and the
    error (``arpz bridge: ...``); None for any other type (the call gets no response: ROS 2
    services have no error reply)."""
    fields = [(f.name, f.base, f.sequence) for f in types.field_defs(response_type)]
    if sorted(fields) != [("message", "string", False), ("success", "bool", False)]:
        return None
    return types.check_service_message(
        response_type, {"success": False, "message": f"arpz bridge: {error}"}
    )


def _merged(old: dict[str, Any] | None, new: dict[str, Any]) -> dict[str, Any]:
    """``new`` with the counts of ``old`` (an earlier incarnation of the topic) added."""
    if old is None:
        return new
    return {k: v + old[k] if isinstance(v, int) and k in old else v for k, v in new.items()}
