"""Calling the robots' services: ``ServiceCaller`` (docs/nodes.md "Services").

A call is a Zenoh query on ``arpz/{fleet}/robot/{robot}/srv/{name}`` carrying a
``ServiceRequest``; the robot (``arpz.robot.services``) answers ``accepted`` when it queued the
call, then the answer (docs/protocol.md "Services"). ``ServiceCaller.call`` returns the typed
response or raises one of the typed errors below; ``call_async`` returns a
``concurrent.futures.Future`` of the same. The CEDDP has one (``CeddpServer.services``), and
``python -m arpz service call`` makes its own.

How a call that gets no answer is told apart (what the caller sees through Zenoh):

- the robot's ``accepted`` came, the answer did not within the timeout: ``ServiceTimeout``
  (``reached`` True): the handler is slow or hung, and the robot counts it too;
- the query ended at once with no reply at all: no queryable this session can see serves the
  key. The robot is gone (``RobotGone``), unless the caller sees it present: then its services
  are hidden from this session, which under access control is the refusal (``ServiceRefused``:
  an identity not allowed to call services is not shown their queryables, so its query ends at
  once instead of timing out; measured through a real router, tests/integration/test_services.py);
- the timeout passed with no reply at all: ``ServiceRefused`` under access control (the
  router dropped the query), else ``ServiceTimeout`` with ``reached`` False (lost on the link,
  or the robot too busy to take it).

Every call is counted per robot and service (``counters``): calls, and how each ended.
"""

from __future__ import annotations

import concurrent.futures
import itertools
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from typing import Any, Final

import msgspec

from arpz.core import keys
from arpz.core.errors import ArpzError, ConfigError
from arpz.core.messages import (
    ANNOUNCE_DECODER,
    DECODE_ERRORS,
    NIL,
    SERVICE_ACCEPTED,
    SERVICE_BUSY,
    SERVICE_FAILED,
    SERVICE_OK,
    SERVICE_REPLY_DECODER,
    SERVICE_TIMEOUT,
    SERVICE_TYPE_ERROR,
    SERVICE_UNKNOWN,
    ServiceCounters,
    ServiceReply,
    ServiceRequest,
    encode,
)
from arpz.core.msgtypes import MessageTypes, MessageValueError
from arpz.core.transport import DeferredQueries, Handle, Transport, TransportError

#: a call's timeout when none is given, s
DEFAULT_TIMEOUT_S: Final = 5.0
#: a query that ends before this share of its timeout ended early: nobody serves the key
_EARLY: Final = 0.9


class ServiceError(ArpzError):
    """A call of ``robot``'s service ``service`` that gave no response (the text says why)."""

    def __init__(self, robot: str, service: str, text: str) -> None:
        super().__init__(text)
        self.robot = robot
        self.service = service


class ServiceTimeout(ServiceError, TimeoutError):
    """No answer within the timeout. ``reached``: the robot took the call (its handler is slow
    or hung, and the robot counts the call a timeout too); False: nothing came back at all."""

    def __init__(self, robot: str, service: str, text: str, *, reached: bool) -> None:
        super().__init__(robot, service, text)
        self.reached = reached


class RobotGone(ServiceError):
    """The robot is not present, or no queryable answers on its service key."""


class ServiceFailed(ServiceError):
    """The handler raised (``error``: its exception, ``Type: text``), or its response did not
    fit the response type."""

    def __init__(self, robot: str, service: str, text: str, *, error: str) -> None:
        super().__init__(robot, service, text)
        self.error = error


class ServiceRefused(ServiceError, PermissionError):
    """Access control kept the call from the robot (this identity may not call services)."""


class ServiceTypeError(ServiceError, TypeError):
    """The request does not fit the service's request type (the text names the field), the
    service type is unknown, or the robot serves this name with another type."""


class NoSuchService(ServiceError, LookupError):
    """The robot is present and serves no service of that name."""


class ServiceBusy(ServiceError):
    """The robot's queue for the service was full: the call was not run."""


@dataclass(frozen=True)
class RobotServices:
    """What a caller knows of a robot: present (None: not known yet) and the services it
    announced, name -> type (None: no announcement seen)."""

    present: bool | None
    services: Mapping[str, str] | None = None


#: robot id -> what the caller knows of it
Directory = Callable[[str], RobotServices]


@dataclass
class CallCounters:
    """One robot's service as its caller counts the calls: each call ends in exactly one of
    the outcomes after ``calls`` (``pending`` until it does)."""

    calls: int = 0
    ok: int = 0
    failed: int = 0
    timeouts: int = 0
    refused: int = 0
    gone: int = 0
    type_errors: int = 0
    unknown: int = 0
    busy: int = 0
    #: the slowest answered call so far, ms (None: none answered)
    latency_ms_max: float | None = None

    @property
    def pending(self) -> int:
        ended = self.ok + self.failed + self.timeouts + self.refused + self.gone
        return self.calls - ended - self.type_errors - self.unknown - self.busy


_OUTCOMES: Final[dict[type[ServiceError], str]] = {
    ServiceFailed: "failed",
    ServiceTimeout: "timeouts",
    ServiceRefused: "refused",
    RobotGone: "gone",
    ServiceTypeError: "type_errors",
    NoSuchService: "unknown",
    ServiceBusy: "busy",
}


class FleetServices:
    """A ``Directory`` of its own, for a caller outside the CEDDP (a tool): the robots'
    presence tokens and their announcements (a plain subscription: all an observer's or
    operator's rights allow), until closed."""

    def __init__(self, transport: Transport, fleet: str) -> None:
        self.fleet = fleet
        self._lock = threading.Lock()
        self._present: set[str] = set()
        #: robots whose token was seen (one gone since is known to be gone)
        self._seen: set[str] = set()
        self._announced: dict[str, dict[str, str]] = {}
        self._started = time.monotonic()
        self._handles: list[Handle] = [
            transport.watch_liveliness(keys.all_presence(fleet), self._on_token),
            transport.subscribe(keys.all_announce(fleet), self._on_announce),
        ]
        #: presence is known once the tokens' history came (a moment after the watch)
        self.history_s = 0.3

    def _on_token(self, key: str, alive: bool) -> None:
        parsed = keys.parse_robot_key(key)
        if parsed is None:
            return
        with self._lock:
            if alive:
                self._present.add(parsed[0])
                self._seen.add(parsed[0])
            else:
                self._present.discard(parsed[0])

    def _on_announce(self, key: str, payload: bytes, _attachment: bytes | None) -> None:
        parsed = keys.parse_robot_key(key)
        if parsed is None:
            return
        try:
            announce = ANNOUNCE_DECODER.decode(payload)
        except DECODE_ERRORS:
            return
        with self._lock:
            self._announced[parsed[0]] = dict(announce.services)

    def __call__(self, robot: str) -> RobotServices:
        with self._lock:
            present: bool | None = robot in self._present
            seen = robot in self._seen
            services = self._announced.get(robot)
        if not present and not seen and time.monotonic() - self._started < self.history_s:
            present = None  # its token may be on its way
        return RobotServices(present, services)

    def robots(self) -> dict[str, RobotServices]:
        """Every robot present or announced: what is known of it."""
        with self._lock:
            names = self._present | set(self._announced)
        return {robot: self(robot) for robot in sorted(names)}

    def wait(
        self,
        done: Callable[[FleetServices], bool],
        timeout_s: float,
        stop: threading.Event | None = None,
    ) -> bool:
        """Wait (polling) until ``done(self)``, ``timeout_s`` or ``stop``; whether done."""
        deadline = time.monotonic() + timeout_s
        while not (stop is not None and stop.is_set()):
            if done(self):
                return True
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.02)
        return False

    def close(self) -> None:
        for handle in self._handles:
            handle.undeclare()
        self._handles = []


class ServiceCaller:
    """Calls robots' services on ``transport`` (a ``DeferredQueries`` transport:
    ``ZenohTransport``, ``MemoryTransport``) and counts every call.

    ``types``: the service types known (the standard ones, and the ``.srv`` files of the
    CEDDP's ``msg_paths``); ``caller``: who calls, as the robot logs it; ``directory``: what is
    known of each robot (the CEDDP passes its registry; without one the caller watches the
    fleet itself, ``FleetServices``); ``access_control``: whether the router enforces access
    control (None: not known), which tells a refused call from a gone robot (module docstring).

    Thread-safe. A call's future is completed on the transport's thread: callbacks added to it
    must be quick."""

    def __init__(
        self,
        transport: Transport,
        fleet: str,
        *,
        types: MessageTypes | None = None,
        caller: str = "",
        directory: Directory | None = None,
        access_control: Callable[[], bool | None] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not isinstance(transport, DeferredQueries):
            raise TypeError(
                f"{transport.__class__.__name__} cannot call services: it has no query whose "
                "replies come later (arpz.core.transport.DeferredQueries)"
            )
        self.transport: DeferredQueries = transport
        self.fleet = keys.check_chunk(fleet, what="fleet")
        self.types = types if types is not None else MessageTypes()
        self.caller = caller
        self._own_directory: FleetServices | None = None
        if directory is None:
            self._own_directory = directory = FleetServices(transport, fleet)
        self.directory: Directory = directory
        self._access_control = access_control or (lambda: None)
        self._clock = clock
        self._lock = threading.Lock()
        self._ids = itertools.count(1)
        self._counters: dict[tuple[str, str], CallCounters] = {}
        #: replies that were not a ``ServiceReply``, or of another call
        self.bad_replies = 0

    # -- calling ------------------------------------------------------------------------------

    def call(
        self,
        robot: str,
        name: str,
        request: object,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        *,
        type: str | None = None,
    ) -> msgspec.Struct:
        """Call ``robot``'s service ``name`` and wait for its response (the response type's
        msgspec Struct), or raise a ``ServiceError``. ``request``: the request type's Struct, a
        dict of its fields or an object with them; ``type``: the service type
        (``std_srvs/srv/Trigger``), by default the one the robot announced. Blocks up to
        ``timeout_s``: never from a Zenoh callback, nor from a planner's ``on_reading`` (it holds
        the CEDDP's ingest): use ``call_async`` there. A robot id or service name that cannot be
        a key chunk raises ``keys.KeyExprError`` (a ValueError), as a command's would."""
        future = self.call_async(robot, name, request, timeout_s, type=type)
        # not ``result(timeout)``: its TimeoutError is the builtin one, a ServiceTimeout's base
        concurrent.futures.wait([future], timeout_s + 5.0)
        if future.done():
            return future.result()
        raise ServiceTimeout(  # the transport never ended the query
            robot, name, f"{robot}/{name}: no end of the call within {timeout_s:g} s", reached=False
        )

    def call_async(
        self,
        robot: str,
        name: str,
        request: object,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        *,
        type: str | None = None,
    ) -> concurrent.futures.Future[msgspec.Struct]:
        """``call`` without waiting: a future of the response (``result()`` raises the
        ``ServiceError``); it is done within ``timeout_s`` (at once for a request that does not
        fit, or a robot known to be gone)."""
        future: concurrent.futures.Future[msgspec.Struct] = concurrent.futures.Future()
        key = keys.service_key(self.fleet, robot, name)
        counters = self._count(robot, name)
        try:
            if not timeout_s > 0:
                raise ServiceTypeError(robot, name, f"timeout must be > 0 s, got {timeout_s}")
            service_type, payload_of = self._prepare(robot, name, request, type)
        except ServiceError as exc:
            self._end(future, counters, exc)
            return future
        call = _Call(self, future, counters, robot, name, service_type, timeout_s)
        payload = payload_of(call.id, int(timeout_s * 1000))
        try:
            self.transport.query(key, payload, call.on_reply, call.on_done, timeout_s=timeout_s)
        except TransportError as exc:
            self._end(future, counters, RobotGone(robot, name, f"{robot}/{name}: {exc}"))
        return future

    def _prepare(
        self, robot: str, name: str, request: object, given: str | None
    ) -> tuple[str, Callable[[int, int], bytes]]:
        """The service type, and the request's payload for a call number and timeout; or the
        ``ServiceError`` the call ends in at once."""
        known = self.directory(robot)
        if known.present is False:
            raise RobotGone(robot, name, f"robot {robot} is not present in fleet {self.fleet!r}")
        announced = known.services.get(name) if known.services is not None else None
        if given is not None and announced is not None and given != announced:
            raise ServiceTypeError(
                robot, name, f"{robot}'s service {name} is {announced}, not {given}"
            )
        service_type = given or announced
        if service_type is None:
            if known.services is not None:
                served = ", ".join(sorted(known.services)) or "none"
                raise NoSuchService(
                    robot, name, f"robot {robot} serves no service {name!r} (it serves: {served})"
                )
            raise ServiceTypeError(
                robot,
                name,
                f"the type of {robot}'s service {name} is not known (no announcement from "
                f"{robot} seen yet): give it",
            )
        try:
            request_type, _ = self.types.service_types(service_type)
            message = self.types.check_service_message(request_type, request)
        except (ConfigError, MessageValueError) as exc:
            raise ServiceTypeError(robot, name, f"{robot}/{name}: {exc}") from None
        body = msgspec.Raw(self.types.encode(message))

        def payload(call_id: int, timeout_ms: int) -> bytes:
            return encode(ServiceRequest(service_type, body, timeout_ms, self.caller, call_id))

        return service_type, payload

    # -- counting -----------------------------------------------------------------------------

    def _count(self, robot: str, name: str) -> CallCounters:
        with self._lock:
            counters = self._counters.setdefault((robot, name), CallCounters())
            counters.calls += 1
            return counters

    def _end(
        self,
        future: concurrent.futures.Future[msgspec.Struct],
        counters: CallCounters,
        outcome: msgspec.Struct | ServiceError,
        latency_ms: float | None = None,
    ) -> None:
        with self._lock:
            if future.done():
                return
            if isinstance(outcome, ServiceError):
                field = next(v for k, v in _OUTCOMES.items() if isinstance(outcome, k))
                setattr(counters, field, getattr(counters, field) + 1)
            else:
                counters.ok += 1
            if latency_ms is not None and not isinstance(outcome, ServiceError):
                counters.latency_ms_max = max(counters.latency_ms_max or 0.0, latency_ms)
        if isinstance(outcome, ServiceError):
            future.set_exception(outcome)
        else:
            future.set_result(outcome)

    def counters(self) -> dict[str, dict[str, CallCounters]]:
        """robot -> service -> its calls so far (copies)."""
        out: dict[str, dict[str, CallCounters]] = {}
        with self._lock:
            for (robot, name), counters in sorted(self._counters.items()):
                out.setdefault(robot, {})[name] = CallCounters(**asdict(counters))
        return out

    def close(self) -> None:
        """Stop watching the fleet (calls in flight still end, by their timeout)."""
        if self._own_directory is not None:
            self._own_directory.close()


class _Call:
    """One call in flight: its replies and its end, on the transport's thread."""

    def __init__(
        self,
        caller: ServiceCaller,
        future: concurrent.futures.Future[msgspec.Struct],
        counters: CallCounters,
        robot: str,
        name: str,
        service_type: str,
        timeout_s: float,
    ) -> None:
        self.caller = caller
        self.future = future
        self.counters = counters
        self.robot, self.name, self.service_type = robot, name, service_type
        self.timeout_s = timeout_s
        self.id = next(caller._ids)
        self.started = caller._clock()
        self.accepted = False

    def on_reply(self, payload: bytes) -> None:
        try:
            reply = SERVICE_REPLY_DECODER.decode(payload)
        except (*DECODE_ERRORS, msgspec.ValidationError):
            reply = None
        if reply is None or reply.id != self.id:
            with self.caller._lock:
                self.caller.bad_replies += 1
            return
        if reply.status == SERVICE_ACCEPTED:
            self.accepted = True
            return
        latency_ms = round((self.caller._clock() - self.started) * 1000, 3)
        self.caller._end(self.future, self.counters, self._outcome(reply), latency_ms)

    def _outcome(self, reply: ServiceReply) -> msgspec.Struct | ServiceError:
        robot, name = self.robot, self.name
        where = f"{robot}/{name}"
        if reply.status == SERVICE_OK:
            _, response_type = self.caller.types.service_types(self.service_type)
            try:
                if bytes(reply.response) == NIL:
                    raise msgspec.ValidationError("no response")
                return self.caller.types.decode(response_type, reply.response)  # type: ignore[no-any-return]
            except (*DECODE_ERRORS, msgspec.ValidationError) as exc:
                text = f"{where}: the response does not fit {response_type}: {exc}"
                return ServiceFailed(robot, name, text, error=text)
        if reply.status == SERVICE_FAILED:
            return ServiceFailed(
                robot, name, f"{where}: the handler failed: {reply.error}", error=reply.error
            )
        if reply.status == SERVICE_TIMEOUT:
            return ServiceTimeout(robot, name, f"{where}: {reply.error}", reached=True)
        if reply.status == SERVICE_UNKNOWN:
            return NoSuchService(robot, name, reply.error or f"{robot} serves no {name}")
        if reply.status == SERVICE_BUSY:
            return ServiceBusy(robot, name, reply.error or f"{where} is busy")
        if reply.status == SERVICE_TYPE_ERROR:
            return ServiceTypeError(robot, name, f"{where}: {reply.error}")
        return ServiceTypeError(robot, name, f"{where}: refused ({reply.status}): {reply.error}")

    def on_done(self) -> None:
        if self.future.done():
            return
        self.caller._end(self.future, self.counters, self._silence())

    def _silence(self) -> ServiceError:
        """Why the call ended with no answer (module docstring)."""
        robot, name = self.robot, self.name
        where = f"{robot}/{name}"
        elapsed = self.caller._clock() - self.started
        access_control = self.caller._access_control()
        if self.accepted:
            if elapsed < _EARLY * self.timeout_s:
                return RobotGone(robot, name, f"{where}: the robot left during the call")
            return ServiceTimeout(
                robot,
                name,
                f"{where}: the robot took the call but did not answer within "
                f"{self.timeout_s:g} s (its handler is slow or hung; the robot counts it)",
                reached=True,
            )
        known = self.caller.directory(robot)
        if elapsed < _EARLY * self.timeout_s:
            if known.present and access_control:
                return ServiceRefused(
                    robot,
                    name,
                    f"{where}: refused by access control: robot {robot} is present, but its "
                    "services are not shown to this identity (an observer may not call "
                    "services: use the CEDDP's or an operator's; docs/security.md)",
                )
            if known.present:
                maybe = " (or access control hides them)" if access_control is None else ""
                return RobotGone(
                    robot,
                    name,
                    f"{where}: robot {robot} is present but serves nothing on "
                    f"{keys.robot_services(self.caller.fleet, robot)}{maybe}: no [[services]], "
                    "or an arpz without services",
                )
            return RobotGone(
                robot,
                name,
                f"{where}: no robot {robot} answers in fleet {self.caller.fleet!r} (not running?)",
            )
        if access_control:
            return ServiceRefused(
                robot,
                name,
                f"{where}: no reply at all within {self.timeout_s:g} s while access control is "
                "in force: the router dropped the call (this identity, or the robot's rules, do "
                "not allow it; docs/security.md)",
            )
        return ServiceTimeout(
            robot,
            name,
            f"{where}: no reply at all within {self.timeout_s:g} s (the request was lost, or "
            "the robot is too busy to take it)",
            reached=False,
        )


def services_summary(
    caller: Mapping[str, Mapping[str, CallCounters]],
    robots: Mapping[str, Mapping[str, ServiceCounters]],
) -> dict[str, dict[str, dict[str, Any]]]:
    """The summary's ``services``: per robot and service, the calls as this caller counted them
    (``caller``, None: it made none) and as the robot reported them (``robot``: every caller's
    calls, None: no report of it)."""
    out: dict[str, dict[str, dict[str, Any]]] = {}
    for robot in sorted(set(caller) | set(robots)):
        mine, theirs = caller.get(robot, {}), robots.get(robot, {})
        out[robot] = {
            name: {
                "caller": {**asdict(mine[name]), "pending": mine[name].pending}
                if name in mine
                else None,
                "robot": msgspec.to_builtins(theirs[name]) if name in theirs else None,
            }
            for name in sorted(set(mine) | set(theirs))
        }
    return out
