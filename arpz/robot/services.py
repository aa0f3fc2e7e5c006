"""A robot's services: request/reply on Zenoh queryables, the team's handlers on workers.

``[[services]] name = "dock"  type = "std_srvs/srv/Trigger"  handler = "mylab.base:dock"`` in a
robot's TOML (docs/nodes.md "Services"). The robot declares one queryable for all its services,
``arpz/{fleet}/robot/{robot}/srv/*`` (a name it does not serve is answered ``unknown``, not left
to time out), and answers each call with ``ServiceReply`` messages (docs/protocol.md
"Services"):

- on Zenoh's queryable thread, at once: a request that is not a ``ServiceRequest``
  (``bad_request``), names no service of this robot (``unknown``), another service type or does
  not fit the request type (``type_error``, naming the field), or finds the service's queue full
  (``busy``); otherwise ``accepted``, and the call is queued;
- on the service's own worker thread (calls of one service never overlap; two services may run at
  once): the handler's answer (``ok`` with the response), or ``failed`` with the exception it
  raised or why its response does not fit the response type; a call whose caller's timeout passed
  while it waited is not run (``timeout``).

Every call is counted per service (``ServiceCounters`` in ``RobotStats.services``): each ends in
exactly one of ok, failed, timeouts, type_errors or busy; a handler that answers after the
caller's timeout is counted a timeout.
"""

from __future__ import annotations

import contextlib
import importlib
import inspect
import logging
import queue
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import msgspec

from arpz.core import keys
from arpz.core.config import ConfigError, RobotConfig, ServiceConfig
from arpz.core.messages import (
    DECODE_ERRORS,
    SERVICE_ACCEPTED,
    SERVICE_BAD_REQUEST,
    SERVICE_BUSY,
    SERVICE_FAILED,
    SERVICE_OK,
    SERVICE_REQUEST_DECODER,
    SERVICE_TIMEOUT,
    SERVICE_TYPE_ERROR,
    SERVICE_UNKNOWN,
    ServiceCounters,
    ServiceReply,
    ServiceRequest,
    encode,
)
from arpz.core.msgtypes import MessageTypes, MessageValueError
from arpz.core.throttled_log import ThrottledLog
from arpz.core.transport import DeferredQueries, Handle, Responder, Transport

log = logging.getLogger(__name__)

#: a service's handler: the request message in, the response out (the response type's Struct,
#: a dict of its fields, or any object with them as attributes)
Handler = Callable[[Any], Any]
#: how long ``close`` waits for a handler still running
_CLOSE_WAIT_S: Final = 1.0
#: how often an idle worker looks whether the host is closing
_IDLE_POLL_S: Final = 0.2


class ServiceConfigError(ConfigError):
    """A configured service whose handler cannot be loaded or made, or whose type is unknown."""


def load_handler(entry: ServiceConfig) -> Handler:
    """The handler ``entry.handler`` names: a function (``module:function``), or a class
    (``module:Class``) made once as ``Class(options)`` whose instances are called with each
    request. Raised here (before the robot joins the fleet) as ``ServiceConfigError`` naming
    the setting."""
    setting = f"services[{entry.name}].handler"
    module_name, _, attr = entry.handler.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ServiceConfigError(
            f"{setting}: cannot import module {module_name!r} ({exc}); install it, or run from "
            "the folder that holds it, or add that folder to PYTHONPATH"
        ) from None
    target: Any = getattr(module, attr, None)
    if target is None:
        raise ServiceConfigError(f"{setting}: module {module_name!r} has no {attr!r}")
    if inspect.isclass(target):
        make: Callable[..., Any] = target
        try:
            made = make(entry.options)
        except Exception as exc:
            raise ServiceConfigError(
                f"{setting}: {entry.handler}({dict(entry.options)!r}) raised {exc!r}"
            ) from exc
        if not callable(made):
            raise ServiceConfigError(
                f"{setting}: instances of {entry.handler} are not callable: give the class a "
                "__call__(self, request) that returns the response"
            )
        handler: Handler = made
        return handler
    if not callable(target):
        raise ServiceConfigError(f"{setting}: {entry.handler} is neither a function nor a class")
    if entry.options:
        raise ServiceConfigError(
            f"services[{entry.name}].options: {entry.handler} is a function, which takes no "
            "options: make the handler a class, made with the options"
        )
    function: Handler = target
    return function


def robot_service_types(
    config: RobotConfig, base_dir: Path, types: MessageTypes | None
) -> MessageTypes | None:
    """The message types a robot's services need: ``types`` (its typed sensors', if any) or
    the standard ones, with the ``.srv`` files of its ``msg_paths`` (``PACKAGE/srv/NAME.srv``
    beside ``PACKAGE/msg/``, relative to the config's folder); ``types`` as given when it
    serves nothing."""
    if not config.services:
        return types
    paths = [base_dir / path for path in config.msg_paths]
    if types is None:
        types = MessageTypes()
        types.add_msg_paths(paths)
    types.add_srv_paths(paths)
    return types


def field_error(text: str, fields: list[str]) -> str:
    """msgspec's error on an ``array_like`` message (``... - at `$[1]```) with the field's
    name instead of its position (``... - at field 'message'``)."""
    head, sep, where = text.rpartition(" - at `$[")
    if not sep:
        return text
    index, _, rest = where.partition("]")
    if not index.isdigit() or int(index) >= len(fields):
        return text
    return f"{head} - at field '{fields[int(index)]}{rest.rstrip('`')}'"


@dataclass
class _Call:
    responder: Responder
    request: ServiceRequest
    message: msgspec.Struct
    #: when the caller's timeout passes (the host's clock)
    deadline_s: float
    queued_s: float


@dataclass
class _Service:
    config: ServiceConfig
    request_type: str
    response_type: str
    handler: Handler
    #: calls waiting for the handler (None: wake up, the host is closing)
    calls: queue.Queue[_Call | None] = field(init=False)
    counters: ServiceCounters = field(default_factory=ServiceCounters)
    thread: threading.Thread | None = None

    def __post_init__(self) -> None:
        self.calls = queue.Queue(maxsize=self.config.queue)


class ServiceHost:
    """Serves a robot's ``[[services]]`` on its ``srv/*`` key (module docstring).

    ``handlers`` (name -> handler) stands in for the configured ones (tests, an embedding
    program); otherwise each is loaded from its ``handler`` setting. Raises
    ``ServiceConfigError`` for a handler that cannot be made or a service type ``types`` does
    not know, before anything is declared."""

    def __init__(
        self,
        config: RobotConfig,
        transport: Transport,
        types: MessageTypes | None,
        *,
        handlers: Mapping[str, Handler] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.fleet, self.robot = config.fleet, config.robot_id
        self.transport = transport
        if config.services and types is None:
            types = MessageTypes()
        self._types = types
        self._clock = clock
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._handle: Handle | None = None
        self._log = ThrottledLog(log, interval_s=60.0)
        #: requests that were not a ``ServiceRequest``, and calls of a name not served here
        self.bad_requests = 0
        self.unknown = 0
        self.services: dict[str, _Service] = {}
        for entry in config.services:
            try:
                request_type, response_type = self.types.service_types(entry.type)
            except ConfigError as exc:
                raise ServiceConfigError(f"services[{entry.name}].type: {exc}") from None
            handler = handlers[entry.name] if handlers and entry.name in handlers else None
            self.services[entry.name] = _Service(
                entry, request_type, response_type, handler or load_handler(entry)
            )

    @property
    def types(self) -> MessageTypes:
        """The message types of the services (there are some whenever this is asked)."""
        assert self._types is not None
        return self._types

    # -- life cycle ---------------------------------------------------------------------------

    def start(self) -> None:
        """Start a worker per service and declare the queryable (nothing when none is
        configured)."""
        if not self.services:
            return
        if not isinstance(self.transport, DeferredQueries):
            raise ServiceConfigError(
                f"services: this transport ({type(self.transport).__name__}) cannot answer "
                "requests later, which a service needs"
            )
        for service in self.services.values():
            service.thread = threading.Thread(
                target=self._work,
                args=(service,),
                name=f"arpz-service-{service.config.name}",
                daemon=True,  # a handler that hangs must not keep the process from exiting
            )
            service.thread.start()
        self._handle = self.transport.serve_deferred(
            keys.robot_services(self.fleet, self.robot), self._on_request
        )
        log.info(
            "serving %s on %s",
            ", ".join(f"{n} ({s.config.type})" for n, s in self.services.items()),
            keys.robot_services(self.fleet, self.robot),
        )

    def close(self) -> None:
        """Stop taking calls, answer those still queued ``failed`` (the robot stops), and wait
        a moment for handlers still running (one that hangs is left to its daemon thread)."""
        if self._handle is not None:
            self._handle.undeclare()
            self._handle = None
        self._stop.set()
        for service in self.services.values():
            with contextlib.suppress(queue.Full):  # a full queue's worker is busy, not asleep
                service.calls.put_nowait(None)
        deadline = time.monotonic() + _CLOSE_WAIT_S
        for service in self.services.values():
            if service.thread is not None:
                service.thread.join(max(0.0, deadline - time.monotonic()))
                if service.thread.is_alive():
                    log.warning(
                        "service %s: its handler is still running at stop (left behind)",
                        service.config.name,
                    )
            while True:
                try:
                    call = service.calls.get_nowait()
                except queue.Empty:
                    break
                if call is not None:
                    self._answer(service, call, failed="the robot stopped before running it")

    # -- what the robot reports ---------------------------------------------------------------

    def announced(self) -> dict[str, str]:
        """name -> service type, for the robot's ``Announce``."""
        return {name: s.config.type for name, s in self.services.items()}

    def counters(self) -> dict[str, ServiceCounters]:
        with self._lock:
            return {name: s.counters for name, s in self.services.items()}

    # -- on Zenoh's queryable thread: answer at once or queue ---------------------------------

    def _on_request(self, key: str, payload: bytes, responder: Responder) -> None:
        name = key.rsplit("/", 1)[-1]
        try:
            request = SERVICE_REQUEST_DECODER.decode(payload)
        except (*DECODE_ERRORS, msgspec.ValidationError) as exc:
            with self._lock:
                self.bad_requests += 1
            self._log.warning("bad request", "service %s: a request that is not one: %s", key, exc)
            _refuse(responder, SERVICE_BAD_REQUEST, f"not a ServiceRequest: {exc}")
            return
        service = self.services.get(name)
        if service is None:
            with self._lock:
                self.unknown += 1
            served = ", ".join(sorted(self.services)) or "none"
            _refuse(
                responder,
                SERVICE_UNKNOWN,
                f"robot {self.robot} serves no service {name!r} (it serves: {served})",
                request_id=request.id,
            )
            return
        message = self._request_message(service, request)
        if isinstance(message, str):
            self._count(service, calls=1, type_errors=1, last_error=message)
            _refuse(
                responder, SERVICE_TYPE_ERROR, message, service.config.type, request_id=request.id
            )
            return
        now = self._clock()
        call = _Call(responder, request, message, now + max(request.timeout_ms, 0) / 1000, now)
        self._count(service, calls=1)
        responder.reply(
            encode(ServiceReply(SERVICE_ACCEPTED, type=service.config.type, id=request.id))
        )
        try:
            service.calls.put_nowait(call)
        except queue.Full:
            text = (
                f"robot {self.robot}'s service {name} is busy: {service.config.queue} call(s) "
                "wait for its handler already (a slow or hung handler?)"
            )
            self._count(service, busy=1, last_error=text)
            _refuse(responder, SERVICE_BUSY, text, service.config.type, request_id=request.id)

    def _request_message(self, service: _Service, request: ServiceRequest) -> str | msgspec.Struct:
        """The request's message of the service's request type, or why it is not one."""
        config = service.config
        if request.type != config.type:
            return (
                f"robot {self.robot}'s service {config.name} is {config.type}, not "
                f"{request.type or '(no type)'}"
            )
        try:
            return self.types.decode(service.request_type, request.request)  # type: ignore[no-any-return]
        except (*DECODE_ERRORS, msgspec.ValidationError) as exc:
            text = field_error(str(exc), self.types.fields(service.request_type))
            return f"the request does not fit {service.request_type}: {text}"

    # -- on the service's worker ---------------------------------------------------------------

    def _work(self, service: _Service) -> None:
        while not self._stop.is_set():
            try:
                call = service.calls.get(timeout=_IDLE_POLL_S)
            except queue.Empty:
                continue
            if call is None:
                break
            if self._clock() > call.deadline_s:
                waited_ms = (self._clock() - call.queued_s) * 1000
                self._answer(
                    service,
                    call,
                    timeout=(
                        f"not run: it waited {waited_ms:.0f} ms for the handler, past the "
                        f"caller's timeout of {call.request.timeout_ms} ms"
                    ),
                )
                continue
            self._run(service, call)

    def _run(self, service: _Service, call: _Call) -> None:
        name = service.config.name
        started = self._clock()
        try:
            result = service.handler(call.message)
        except Exception as exc:
            text = f"{type(exc).__name__}: {exc}"
            self._log.exception(f"{name}: {text}", "service %s: the handler raised %s", name, text)
            self._answer(service, call, failed=text, started=started)
            return
        try:
            response = self.types.check_service_message(service.response_type, result)
        except MessageValueError as exc:
            text = f"the handler's response does not fit {service.response_type}: {exc}"
            self._log.warning(f"{name}: response", "service %s: %s", name, text)
            self._answer(service, call, failed=text, started=started)
            return
        self._answer(service, call, response=response, started=started)

    def _answer(
        self,
        service: _Service,
        call: _Call,
        *,
        response: msgspec.Struct | None = None,
        failed: str = "",
        timeout: str = "",
        started: float | None = None,
    ) -> None:
        """Count the call's end and send its answer (a late one too: the caller ignores it)."""
        now = self._clock()
        handler_ms = None if started is None else round((now - started) * 1000, 3)
        late = started is not None and now > call.deadline_s
        if timeout or late:
            self._count(
                service,
                handler_ms=handler_ms,
                timeouts=1,
                last_error=timeout
                or (
                    f"answered after {handler_ms} ms, past the caller's timeout of "
                    f"{call.request.timeout_ms} ms"
                ),
            )
        elif failed:
            self._count(service, handler_ms=handler_ms, failed=1, last_error=failed)
        else:
            self._count(service, handler_ms=handler_ms, ok=1)
        if response is not None:
            reply = ServiceReply(
                SERVICE_OK,
                response=msgspec.Raw(self.types.encode(response)),
                type=service.config.type,
                id=call.request.id,
                handler_ms=handler_ms,
            )
        else:
            reply = ServiceReply(
                SERVICE_TIMEOUT if timeout else SERVICE_FAILED,
                error=timeout or failed,
                type=service.config.type,
                id=call.request.id,
                handler_ms=handler_ms,
            )
        call.responder.reply(encode(reply))
        call.responder.finish()

    def _count(
        self,
        service: _Service,
        *,
        handler_ms: float | None = None,
        last_error: str | None = None,
        **added: int,
    ) -> None:
        """Add ``added`` to the service's counters (``ServiceCounters`` fields), note a handler
        run's time and the last error."""
        with self._lock:
            counters = service.counters
            changes: dict[str, Any] = {k: getattr(counters, k) + n for k, n in added.items()}
            if handler_ms is not None:
                changes["handler_ms_max"] = max(counters.handler_ms_max or 0.0, handler_ms)
            if last_error is not None:
                changes["last_error"] = last_error
            service.counters = msgspec.structs.replace(counters, **changes)


def _refuse(
    responder: Responder, status: str, error: str, service_type: str = "", *, request_id: int = 0
) -> None:
    responder.reply(encode(ServiceReply(status, error=error, type=service_type, id=request_id)))
    responder.finish()
