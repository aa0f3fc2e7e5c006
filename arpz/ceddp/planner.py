"""The planner interface of the CEDDP, a team's planners from config, and the Hello relay of
seed 001 Fig. 9.

A planner sees only what cache control let through (``on_reading``), Hello probes
(``on_hello``) and fleet changes (``on_robot``); it acts by sending commands through its
``commands`` sink. It runs on the CEDDP's ingest worker thread, never on a Zenoh callback, so it
may take its time, but a slow planner delays ingest (which is measured and reported).

A team's planners are named in the CEDDP's TOML (``[[planners]] class = "mylab.dock:Dock"``,
docs/nodes.md) and run behind a ``GuardedPlanner``: an exception in one is counted, logged with
its traceback once per cause, and never stops the CEDDP or the planners beside it.
"""

from __future__ import annotations

import collections
import concurrent.futures
import logging
import threading
import time
import traceback
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import msgspec

from arpz.ceddp.services import ServiceCaller
from arpz.core import keys
from arpz.core.errors import ConfigError
from arpz.core.messages import (
    Command,
    CommandContract,
    CommandValue,
    Hello,
    MessageCommand,
    SensorValue,
    Telemetry,
)
from arpz.core.msgtypes import MessageTypes, MessageValueError
from arpz.core.throttled_log import ThrottledLog
from arpz.runtime.plugins import load_class

log = logging.getLogger(__name__)
_throttled = ThrottledLog(log)


@dataclass(frozen=True, slots=True)
class Reading:
    """One reading that cache control let through. ``value``: a scalar kind's value, or a typed
    topic's whole message (the msgspec Struct of its ROS 2 type, arpz.core.msgtypes)."""

    robot: str
    topic: str
    value: SensorValue | msgspec.Struct
    #: when the robot read it, on the robot's clock (``arrival_ns`` is the CEDDP's)
    stamp_ns: int
    arrival_ns: int
    seq: int
    #: the writer that sent it: ``robot:incarnation`` (a restarted robot writes as a new one)
    writer: str = ""

    @property
    def incarnation(self) -> str:
        """The robot process's incarnation (new at every start)."""
        return self.writer.partition(":")[2]


class CommandSink(Protocol):
    def send(self, robot: str, name: str, payload: bytes) -> None:
        """Publish ``payload`` on the robot's ``cmd/{name}`` key."""


class PlannerCommands:
    """What a team's planner sends commands through (``self.commands``): ``send`` a command on
    a robot's ``cmd/{name}``. For a command the robot's actuator accepts as a value, ``value`` is
    a float, bool, string or list of floats (``[v, omega]`` on "velocity"); for a typed one (the
    actuator's ``command_types``, announced by the robot), a message of that type (a dict of its
    fields, or its Struct), checked here: a message that does not fit raises
    ``MessageValueError`` naming the field, so the planner's guard counts it. Every command is
    counted by the CEDDP's downlink and reconciled with what the robot received; a command for
    a name the robot did not announce is refused and counted.

    One instance is shared by every configured planner, so that the command seqs of one key
    stay one sequence (a receiver in plain mode counts its loss from them)."""

    def __init__(
        self,
        sink: CommandSink,
        writer: str,
        *,
        command_type: Callable[[str, str], str | None] = lambda robot, name: None,
        types: MessageTypes | None = None,
    ) -> None:
        self.sink = sink
        self.writer = writer
        self._command_type = command_type
        self._types = types
        self._seqs: dict[tuple[str, str], int] = {}
        self._lock = threading.Lock()

    def send(
        self, robot: str, name: str, value: CommandValue | Mapping[str, Any] | msgspec.Struct
    ) -> None:
        msg_type = self._command_type(robot, name)
        raw: msgspec.Raw | None = None
        if msg_type is not None:
            if self._types is None:
                self._types = MessageTypes()
            message = self._types.check(msg_type, value, stamp_ns=time.time_ns())
            raw = msgspec.Raw(self._types.encode(message))
        elif isinstance(value, Mapping | msgspec.Struct):
            raise MessageValueError(
                f"robot {robot} takes {name} as a value (a float, bool, string or list of "
                "floats), not a message: its actuator names no type for it in command_types"
            )
        with self._lock:  # numbered once it is sure to leave: a refused one leaves no hole
            seq = self._seqs[(robot, name)] = self._seqs.get((robot, name), 0) + 1
        payload: msgspec.Struct = (
            Command(self.writer, seq, time.time_ns(), value)  # type: ignore[arg-type]
            if raw is None
            else MessageCommand(self.writer, seq, time.time_ns(), raw)
        )
        self.sink.send(robot, name, msgspec.msgpack.encode(payload))


class Planner:
    """Base planner: ignores everything. Subclass and override what you need.

    A planner named in the CEDDP's config is made as ``cls(options)`` (the TOML's ``options``
    table) and given the fleet's command sink as ``self.commands`` before ``start``."""

    #: set True to be told of readings cache control discarded (``on_unchanged``): a planner that
    #: judges freshness needs to know an unchanged topic is still alive
    wants_unchanged: bool = False
    #: the commands it sends: name -> the ROS 2 type of its messages, or "value" (a float, bool,
    #: string or list of floats). A robot whose actuator takes one of them as another type
    #: refuses to start, naming the planner (docs/nodes.md)
    sends: Mapping[str, str] = {}

    def __init__(self, options: Mapping[str, Any] | None = None) -> None:
        self.options: Mapping[str, Any] = options or {}
        self.commands: PlannerCommands | None = None
        self.services: ServiceCaller | None = None

    def attach(self, commands: PlannerCommands, services: ServiceCaller | None = None) -> None:
        """Hand the planner the sink its commands go through and the caller of robots'
        services (before ``start``)."""
        self.commands = commands
        self.services = services

    def robot_service(
        self,
        robot: str,
        name: str,
        request: object,
        timeout_s: float = 5.0,
        *,
        type: str | None = None,
    ) -> msgspec.Struct:
        """Call ``robot``'s service ``name`` and wait for its typed response, or raise a
        ``ServiceError`` (``ServiceTimeout``, ``RobotGone``, ``ServiceFailed``,
        ``ServiceRefused``, ``ServiceTypeError``...; docs/nodes.md "Services"). It blocks: call
        it from a thread of the planner's own or from ``tick``, never from ``on_reading`` (it
        would hold the CEDDP's ingest): there, use ``robot_service_async``."""
        return self._caller().call(robot, name, request, timeout_s, type=type)

    def robot_service_async(
        self,
        robot: str,
        name: str,
        request: object,
        timeout_s: float = 5.0,
        *,
        type: str | None = None,
    ) -> concurrent.futures.Future[msgspec.Struct]:
        """``robot_service`` without waiting: a future of the response, done within
        ``timeout_s`` (its callbacks run on a Zenoh thread: keep them quick)."""
        return self._caller().call_async(robot, name, request, timeout_s, type=type)

    def _caller(self) -> ServiceCaller:
        if self.services is None:
            raise RuntimeError("this planner was not attached to a CEDDP: no services to call")
        return self.services

    def on_unchanged(self, robot: str, topic: str, stamp_ns: int) -> None:
        """A reading equal to the cached one arrived (and was discarded) at source time stamp_ns."""

    def start(self) -> None:
        """Called once when the server starts (start a thread here if the planner needs one)."""

    def stop(self) -> None:
        """Called once when the server stops, before the summary is made."""

    def on_telemetry(self, robot: str, telemetry: Telemetry) -> None:
        """A simulated robot's true pose: only for judging and drawing, never for planning."""

    def on_reading(self, reading: Reading) -> None:
        """A de-duplicated sensor reading."""

    def on_hello(self, robot: str, hello: Hello) -> None:
        """A Hello probe published by ``robot``."""

    def on_robot(self, robot: str, alive: bool) -> None:
        """A robot joined (alive) or left."""

    def tick(self, now_s: float) -> None:
        """Called periodically by the server (metrics period)."""


class CostlyPlanner(Planner):
    """A stand-in for a heavy planning algorithm: every reading costs ``cost_us`` of CPU time
    on the ingest thread (``[overload] planner_cost_us``). It gives a CEDDP a known, small
    capacity, so that overload and its recovery can be rehearsed and tested with few robots."""

    def __init__(self, cost_us: float) -> None:
        self.cost_s = cost_us / 1e6

    def on_reading(self, reading: Reading) -> None:
        until = time.thread_time() + self.cost_s
        while time.thread_time() < until:
            pass


@dataclass
class HelloRelayCounters:
    forwarded_to_relay: int = 0
    returned_to_origin: int = 0
    #: Hellos that could not be forwarded because no relay robot is present
    no_relay: int = 0
    bad_stage: int = 0
    #: Hellos naming an origin that is not a robot id (forged or corrupt): dropped
    bad_origin: int = 0


class HelloRelay(Planner):
    """Origin -> CEDDP -> relay -> CEDDP -> origin, each hop a real publish through the router.

    The relay is the configured robot, or if none is configured, the origin itself (a one-robot
    fleet still measures a full four-hop round trip).
    """

    def __init__(self, sink: CommandSink, writer: str, relay: str | None = None) -> None:
        self.sink = sink
        self.writer = writer
        self.relay = relay
        self.counters = HelloRelayCounters()
        self._present: set[str] = set()
        self._seqs: dict[str, int] = {}
        self._lock = threading.Lock()

    def on_robot(self, robot: str, alive: bool) -> None:
        with self._lock:
            (self._present.add if alive else self._present.discard)(robot)

    def on_hello(self, robot: str, hello: Hello) -> None:
        try:
            keys.check_chunk(hello.origin, what="Hello origin")
        except keys.KeyExprError:
            self.counters.bad_origin += 1
            log.warning("Hello from %s with an invalid origin %r dropped", robot, hello.origin)
            return
        if hello.stage == 0:
            relay = self.relay or hello.origin
            with self._lock:
                known = relay in self._present
            if not known:  # forwarding to an absent robot would lose it silently in Zenoh
                self.counters.no_relay += 1
                _throttled.warning(
                    f"no relay {relay}",
                    "Hello from %s dropped: its relay robot %r is not connected (%d so far); "
                    "set [hello] relay in the CEDDP config to a robot of this fleet",
                    robot,
                    relay,
                    self.counters.no_relay,
                )
                return
            self._forward(relay, hello, stage=1)
            self.counters.forwarded_to_relay += 1
        elif hello.stage == 2:
            self._forward(hello.origin, hello, stage=3)
            self.counters.returned_to_origin += 1
        else:
            self.counters.bad_stage += 1
            log.warning("Hello with stage %d published by %s ignored", hello.stage, robot)

    def _forward(self, robot: str, hello: Hello, *, stage: int) -> None:
        # seq counts per key (docs/protocol.md): one counter per robot's cmd/hello
        seq = self._seqs[robot] = self._seqs.get(robot, 0) + 1
        hop = msgspec.structs.replace(
            hello, writer=self.writer, seq=seq, stamp_ns=time.time_ns(), stage=stage
        )
        self.sink.send(robot, keys.HELLO, msgspec.msgpack.encode(hop))


#: at most this many distinct causes are kept per planner (a planner raising a new message on
#: every reading must not grow the CEDDP's memory); more are counted under "other causes"
MAX_CAUSES = 32


class GuardedPlanner(Planner):
    """A team's planner, kept from taking the CEDDP down with it.

    Every callback runs inside ``try``: an exception is counted (per cause: the callback and the
    exception's type and message), logged with its traceback the first time that cause is seen,
    then once a minute with the count while it lasts; the CEDDP, its ingest and the other
    planners go on. ``faults()`` is what the summary and the status page show."""

    def __init__(self, inner: Planner, name: str, on_first: Callable[[str], None]) -> None:
        super().__init__(inner.options)
        self.inner = inner
        self.name = name
        self.wants_unchanged = inner.wants_unchanged
        self._on_first = on_first
        self._lock = threading.Lock()
        self._causes: collections.Counter[str] = collections.Counter()
        self.errors = 0
        self._throttled = ThrottledLog(log, interval_s=60.0)

    def _call(self, callback: str, *args: Any) -> None:
        try:
            getattr(self.inner, callback)(*args)
        except Exception as exc:  # a team's code: anything may come out of it
            self._fault(callback, exc)

    def _fault(self, callback: str, exc: Exception) -> None:
        cause = f"{callback}: {type(exc).__name__}: {exc}"[:200]
        with self._lock:
            self.errors += 1
            first = cause not in self._causes
            if first and len(self._causes) >= MAX_CAUSES:
                cause, first = "other causes", False
            self._causes[cause] += 1
            count = self._causes[cause]
        if first:
            log.error(
                "planner %s raised in %s (counted; the CEDDP goes on):\n%s",
                self.name,
                callback,
                "".join(traceback.format_exception(exc)).rstrip(),
            )
            self._on_first(f"planner {self.name} raised {cause} (traceback in the log)")
        else:
            self._throttled.warning(
                f"{self.name} {cause}", "planner %s: %s, %d times", self.name, cause, count
            )

    @property
    def sends(self) -> Mapping[str, str]:  # type: ignore[override]
        return self.inner.sends

    def faults(self) -> dict[str, object]:
        with self._lock:
            return {"errors": self.errors, "causes": dict(self._causes)}

    def attach(self, commands: PlannerCommands, services: ServiceCaller | None = None) -> None:
        self.inner.attach(commands, services)

    def start(self) -> None:
        self._call("start")

    def stop(self) -> None:
        self._call("stop")

    def on_telemetry(self, robot: str, telemetry: Telemetry) -> None:
        self._call("on_telemetry", robot, telemetry)

    def on_reading(self, reading: Reading) -> None:
        self._call("on_reading", reading)

    def on_unchanged(self, robot: str, topic: str, stamp_ns: int) -> None:
        self._call("on_unchanged", robot, topic, stamp_ns)

    def on_hello(self, robot: str, hello: Hello) -> None:
        self._call("on_hello", robot, hello)

    def on_robot(self, robot: str, alive: bool) -> None:
        self._call("on_robot", robot, alive)

    def tick(self, now_s: float) -> None:
        self._call("tick", now_s)


def make_planner(
    spec: str,
    options: Mapping[str, Any],
    commands: PlannerCommands,
    *,
    setting: str,
    on_first_fault: Callable[[str], None],
    services: ServiceCaller | None = None,
) -> GuardedPlanner:
    """The planner ``spec`` names, made with its options, attached and guarded."""
    cls = load_class(spec, Planner, setting=setting)
    try:
        planner = cls(options)
    except Exception as exc:
        raise PlannerConfigError(f"{setting}: {spec}({dict(options)!r}) raised {exc!r}") from exc
    planner.attach(commands, services)
    return GuardedPlanner(planner, spec.rpartition(":")[2], on_first_fault)


class PlannerConfigError(ConfigError):
    """A configured planner that cannot be made from its options."""


def command_contract(ceddp: str, planners: list[GuardedPlanner]) -> CommandContract:
    """What the team's planners declare they send, for a robot to check at start-up."""
    sends: dict[str, dict[str, str]] = {}
    for planner in planners:
        for name, msg_type in planner.sends.items():
            sends.setdefault(name, {})[planner.name] = msg_type
    return CommandContract(ceddp, sends)
