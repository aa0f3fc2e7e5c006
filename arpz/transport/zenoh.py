"""The Zenoh seam: the only module of arpz's runtime that imports zenoh.

``ZenohTransport`` implements ``arpz.core.transport.Transport`` over a Zenoh session, and every
Zenoh error that crosses the seam comes out as ``TransportError`` (or ``ConfigError`` for a
configuration Zenoh refuses), so callers never need ``except Exception``. The rest of the module
reads Zenoh JSON5 configs into sentences that name the file and the field.
"""

from __future__ import annotations

import collections
import contextlib
import json
import logging
import os
import re
import socket
import stat
import struct
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import zenoh

from arpz.core.endpoints import check_endpoints, endpoint_address
from arpz.core.errors import ConfigError
from arpz.core.link_sizes import link_sizes, session_batch_size
from arpz.core.protocol import bundle
from arpz.core.transport import (
    DataCallback,
    DeferredQueryHandler,
    DoneCallback,
    Handle,
    LivelinessCallback,
    Publisher,
    PullSubscriber,
    QueryHandler,
    Received,
    ReplyCallback,
    SessionSettings,
    TransportError,
)

log = logging.getLogger(__name__)


@contextlib.contextmanager
def _translated(what: str) -> Iterator[None]:
    """Zenoh's errors as ``TransportError``, saying what was being done."""
    try:
        yield
    except zenoh.ZError as exc:
        raise TransportError(f"{what}: {zenoh_message(exc)}") from exc


_RUST_LOCATION = re.compile(r"\s+at /\S+\.rs:\d+\.?")


def zenoh_message(exc: BaseException) -> str:
    """A Zenoh error without the Rust source location it ends with."""
    return _RUST_LOCATION.sub("", str(exc)).strip()


def config_value(conf: zenoh.Config, key: str) -> object:
    """One entry of a Zenoh config as a Python value (None if absent)."""
    try:
        return json.loads(conf.get_json(key))
    except (zenoh.ZError, ValueError):
        return None


def tls_identity(conf: zenoh.Config) -> str:
    """Who a session claims to be over TLS, for an error message: its certificate file."""
    cert = config_value(conf, "transport/link/tls/connect_certificate")
    return f"TLS identity {cert}" if isinstance(cert, str) else "no TLS client certificate"


#: the file-valued keys of Zenoh's ``transport/link/tls`` section
TLS_FILE_KEYS = (
    "root_ca_certificate",
    "connect_certificate",
    "connect_private_key",
    "listen_certificate",
    "listen_private_key",
)


def load_zenoh_config(path: str, *, source: str) -> zenoh.Config:
    """The JSON5 file ``zenoh_config`` names, checked: it exists, parses, its TLS files exist
    and its endpoints are well formed. ``source``: the TOML that names it, for the message."""
    where = f"{source}: field 'zenoh_config'"
    file = Path(path)
    if not file.is_file():
        raise ConfigError(f"{where}: {path}: no such file")
    try:
        conf = zenoh.Config.from_file(path)
    except zenoh.ZError as exc:
        message = zenoh_message(exc)
        raise ConfigError(f"{where}: {path} is not a valid Zenoh config: {message}") from None
    for key in TLS_FILE_KEYS:
        value = config_value(conf, f"transport/link/tls/{key}")
        if isinstance(value, str) and not Path(value).is_file():
            raise ConfigError(f"{path}: transport.link.tls.{key}: {value}: no such file")
    for section in ("connect", "listen"):
        endpoints = config_value(conf, f"{section}/endpoints")
        if isinstance(endpoints, list):
            try:
                check_endpoints([str(e) for e in endpoints], field=f"{section}.endpoints")
            except ValueError as exc:
                raise ConfigError(f"{path}: {exc}") from None
    return conf


def uses_tls(conf: zenoh.Config) -> bool:
    """Whether a Zenoh config sets up TLS (any certificate or key file)."""
    return any(
        isinstance(config_value(conf, f"transport/link/tls/{key}"), str) for key in TLS_FILE_KEYS
    )


def access_control_enabled(conf: zenoh.Config) -> bool:
    """Whether a Zenoh config turns ``access_control`` on (its ``enabled`` field is true)."""
    return config_value(conf, "access_control/enabled") is True


def config_security(path: str) -> tuple[bool, bool] | None:
    """(access control enabled, TLS set up) of the Zenoh config file ``path``, for a process to
    report about itself; None when the file cannot be read (its loader already said why)."""
    try:
        conf = zenoh.Config.from_file(path)
    except zenoh.ZError:
        return None
    return access_control_enabled(conf), uses_tls(conf)


def config_endpoints(conf: zenoh.Config, section: str) -> list[str]:
    """The ``connect`` or ``listen`` endpoints a Zenoh config file lists (empty if none)."""
    endpoints = config_value(conf, f"{section}/endpoints")
    return [str(e) for e in endpoints] if isinstance(endpoints, list) else []


#: Zenoh's batch size: one datagram on a UDP link (set by arpz from the endpoints)
BATCH_SIZE_KEY = "transport/link/tx/batch_size"


def build_config(settings: SessionSettings) -> zenoh.Config:
    if settings.mode not in ("client", "peer", "router"):
        raise TransportError(f"mode must be client, peer or router, not {settings.mode!r}")
    try:
        conf = (
            zenoh.Config.from_file(settings.config_file) if settings.config_file else zenoh.Config()
        )
        conf.insert_json5("mode", json.dumps(settings.mode))
        conf.insert_json5("scouting/multicast/enabled", json.dumps(settings.multicast_scouting))
        if settings.listen:
            conf.insert_json5("listen/endpoints", json.dumps(list(settings.listen)))
        if settings.connect:
            conf.insert_json5("connect/endpoints", json.dumps(list(settings.connect)))
        defaults: dict[str, object] = dict(settings.defaults or {})
        # one radio frame per UDP datagram (arpz.core.link_sizes): a lost frame costs one fragment,
        # not a 64 KiB batch; a config file's own batch size wins, and so does ``extra``
        batch_size = session_batch_size(settings.connect, settings.listen)
        if batch_size is not None:
            defaults.setdefault(BATCH_SIZE_KEY, batch_size)
        if defaults:
            zenoh_default = zenoh.Config()
            for key, value in defaults.items():
                # the file's own value wins; one equal to Zenoh's default cannot be told apart
                # from no value at all, and is replaced
                if config_value(conf, key) == config_value(zenoh_default, key):
                    conf.insert_json5(key, json.dumps(value))
        for key, value in settings.extra.items():
            conf.insert_json5(key, json.dumps(value))
    except zenoh.ZError as exc:
        raise TransportError(f"invalid Zenoh configuration: {zenoh_message(exc)}") from exc
    return conf


class _Link:
    """What every handle of one transport shares: whether its session is being replaced (from
    the close of the old one until the new one is open and everything is declared on it), and
    how much the session delivered to callbacks (``ZenohTransport.delivered``)."""

    __slots__ = ("delivered", "down")

    def __init__(self) -> None:
        self.down = False
        self.delivered = 0


#: ``declare(session, current)``: the Zenoh object of a handle in ``session``; its callbacks
#: call ``current()`` first and drop what they get once the handle was declared again elsewhere
_Declare = Callable[[zenoh.Session, Callable[[], bool]], Any]


class _Declared:
    """Something declared on the session that survives a reopen: ``attach`` declares it
    (again) on a session; the caller's handle stays the same object."""

    def __init__(self, declare: _Declare) -> None:
        self._declare = declare
        self._inner: Any = None
        self._lock = threading.Lock()
        self._done = False
        #: which declaration is in force: a callback of an older one drops what it gets (a
        #: session closed on a dead link may still deliver once the link comes back)
        self.generation = 0

    def _current(self, generation: int) -> Callable[[], bool]:
        def current() -> bool:
            return self.generation == generation

        return current

    def attach(self, session: zenoh.Session) -> None:
        """Declare on ``session`` (raises ``zenoh.ZError``); the previous declaration's
        callbacks go quiet first."""
        with self._lock:
            if self._done:
                return
            self.generation += 1
            current = self._current(self.generation)
        self._superseded()
        inner = self._declare(session, current)
        with self._lock:
            done = self._done
            if not done:
                self._inner = inner
        if done:  # undeclared meanwhile
            self._undeclare(inner)
            return
        self._attached()

    def detach(self) -> None:
        """The session is being replaced: what must let go of the old one now does (a pull
        subscriber's FIFO, where a receiver may be blocked); the rest goes with the session."""

    def _superseded(self) -> None:
        """The declaration in force was just replaced (its callbacks drop from now on)."""

    def _attached(self) -> None:
        """The new declaration is in force."""

    @staticmethod
    def _undeclare(inner: Any) -> None:
        if inner is None:
            return
        try:
            inner.undeclare()
        except (zenoh.ZError, RuntimeError) as exc:  # closed session, or a receiver still blocked
            log.debug("undeclare failed: %s", exc)

    def undeclare(self) -> None:
        with self._lock:
            if self._done:
                return
            self._done = True
            inner = self._inner
        self._undeclare(inner)
        self._attached()  # wakes whoever waits for a new declaration


class _ZenohPublisher(_Declared):
    def __init__(self, declare: _Declare, link: _Link) -> None:
        super().__init__(declare)
        self._link = link
        #: puts dropped while the transport was down (being reopened)
        self.dropped_while_down = 0

    def put(self, payload: bytes, *, attachment: bytes | None = None) -> None:
        try:  # not ``_translated``: once per sample on a robot's hot path
            if attachment is None:
                self._inner.put(payload)
            else:
                self._inner.put(payload, attachment=attachment)
        except (zenoh.ZError, AttributeError) as exc:  # AttributeError: declared while down
            if self._link.down and not self._done:
                self.dropped_while_down += 1  # as a congested link drops it (DROP)
                return
            raise TransportError(f"put: {zenoh_message(exc)}") from exc

    @property
    def matching(self) -> bool:
        if self._inner is None:
            return False
        try:
            status = self._inner.matching_status
        except zenoh.ZError as exc:  # closed session
            log.debug("matching status after close: %s", exc)
            return False
        # the stubs say bool; zenoh-python 1.x returns a MatchingStatus with ``.matching``
        return bool(getattr(status, "matching", status))


class _ZenohPullSubscriber(_Declared):
    def __init__(self, declare: _Declare, keep: Callable[[str], bool] | None, link: _Link) -> None:
        super().__init__(declare)
        self._link = link
        #: (generation, try_recv, recv) of the declaration in force, swapped as one
        self._bound: tuple[int, Callable[[], zenoh.Sample | None], Callable[[], zenoh.Sample]]
        self._bound = (0, _nothing, _closed_recv)
        self._rebound = threading.Condition()
        #: a widened subscription's filter (``bundle.subscription``)
        self._keep = keep
        #: a bundle's entries not yet received (one receiving thread, so no lock)
        self._pending: collections.deque[Received] = collections.deque()
        #: the Zenoh sample last taken from the FIFO: its timestamp, read only when asked
        self._last: zenoh.Sample | None = None

    def detach(self) -> None:
        with self._lock:
            inner = self._inner
        self._undeclare(inner)  # its FIFO closes: a blocked ``recv`` raises, then waits

    def _attached(self) -> None:
        with self._rebound:
            inner = self._inner
            if inner is not None and not self._done:
                # the handler's own methods, not the subscriber's: a thread blocked in the
                # subscriber's recv keeps it borrowed and undeclare fails ("Already borrowed");
                # blocked in the handler's, undeclare closes the channel and that recv raises
                self._bound = (self.generation, inner.handler.try_recv, inner.handler.recv)
            self._rebound.notify_all()

    def _received(self, sample: zenoh.Sample) -> Received | None:
        """The sample, or the first of a bundle's entries (the rest wait in ``_pending``); None
        when a widened subscription's filter refuses everything it carried."""
        att = sample.attachment
        key = str(sample.key_expr)
        payload = sample.payload.to_bytes()
        attachment = att.to_bytes() if att is not None else None
        if self._keep is None and not key.endswith(bundle.CHUNK):
            return key, payload, attachment
        items = bundle.expand(key, payload, attachment, self._keep)
        if not items:
            return None
        self._pending.extend(items[1:])
        return items[0]

    def _survives(self, generation: int) -> bool:
        """A receive on the declaration ``generation`` failed: whether that is a reopen (wait
        for the new declaration) rather than the end (undeclared, transport closed)."""
        return not self._done and (self._link.down or self._bound[0] != generation)

    def _await_new(self, generation: int) -> None:
        with self._rebound:
            while self._bound[0] == generation and not self._done:
                self._rebound.wait(0.5)

    # try/except rather than ``_translated``: this runs once per sample on the ingest path, and
    # a generator context manager costs more than the rest of the call
    def _next(self, blocking: bool) -> Received | None:
        if self._pending:
            return self._pending.popleft()
        while True:
            generation, try_recv, recv = self._bound
            try:
                sample = recv() if blocking else try_recv()
            except zenoh.ZError as exc:
                if not self._survives(generation):
                    raise TransportError(f"receive: {zenoh_message(exc)}") from exc
                if not blocking:
                    return None
                self._await_new(generation)
                continue
            if sample is None:
                return None
            self._last = sample
            item = self._received(sample)
            if item is not None:
                return item

    def try_recv(self) -> Received | None:
        return self._next(False)

    def recv(self) -> Received:
        """Blocks (across a reopen too); raises ``TransportError`` once the subscriber is
        undeclared and drained."""
        item = self._next(True)
        assert item is not None  # a blocking receive returns a sample or raises
        return item

    def waited_ns(self) -> int | None:
        """From the timestamp a router gives every sample it receives (Zenoh's default for
        routers): exact where this session is the router that timestamped it (a CEDDP), else
        off by the router's clock offset. None: no sample yet, or it carries no timestamp."""
        sample = self._last
        stamp = sample.timestamp if sample is not None else None
        if stamp is None:
            return None
        # uhlc's NTP64 counts from the Unix epoch
        return max(0, time.time_ns() - stamp.get_time_as_ntp64().as_nanos())


def _nothing() -> None:
    return None


def _closed_recv() -> zenoh.Sample:
    raise zenoh.ZError("not declared yet")


class _Watcher(_Declared):
    """A liveliness subscriber that remembers which tokens it saw alive. Declared again on a
    new session (a reopen), its history says again which tokens are alive (the caller sees
    them alive once more), and ``reconcile`` tells the caller which of those it saw alive
    before are gone (a CEDDP that restarted during the outage: its old readers). A token
    still alive is never reported vanished: a reliable writer keeps its reader's state, and a
    KEEP_ALL history waits for that reader instead of dropping what it has not acknowledged
    (a blanket "everything vanished" lost samples in tests/integration/test_faults.py)."""

    def __init__(self, key_expr: str, callback: LivelinessCallback, link: _Link) -> None:
        self._key_expr = key_expr
        self._callback = callback
        self._alive: set[str] = set()
        #: seen alive on a session that was replaced, not yet seen on the new one
        self._before: set[str] = set()
        #: held while the caller's callback runs: what a reopen reports comes after anything
        #: the old declaration delivered, never between its check and its call
        self._calls = threading.Lock()

        def declare(session: zenoh.Session, current: Callable[[], bool]) -> Any:
            def on_change(sample: zenoh.Sample) -> None:
                key = str(sample.key_expr)
                alive = sample.kind == zenoh.SampleKind.PUT
                with self._calls:
                    if not current():
                        return
                    link.delivered += 1
                    if alive:
                        self._alive.add(key)
                    else:
                        self._alive.discard(key)
                    self._before.discard(key)
                    callback(key, alive)

            return session.liveliness().declare_subscriber(key_expr, on_change, history=True)

        super().__init__(declare)

    def _superseded(self) -> None:
        with self._calls:
            self._before |= self._alive
            self._alive = set()

    def ask(self, session: zenoh.Session) -> tuple[threading.Event, set[str]]:
        """Ask the new session which tokens are alive now: (set once answered, the keys)."""
        done = threading.Event()
        keys: set[str] = set()

        def on_reply(reply: zenoh.Reply) -> None:
            sample = reply.ok
            if sample is not None:
                keys.add(str(sample.key_expr))

        session.liveliness().get(
            self._key_expr, zenoh.handlers.Callback(on_reply, done.set), timeout=_RECONCILE_S
        )
        return done, keys

    def reconcile(self, alive_now: set[str] | None) -> None:
        """Tell the caller that what it saw alive before the reopen and is not alive now
        vanished (``alive_now`` None: the question was not answered, nothing is told)."""
        if alive_now is None:
            return
        with self._calls:
            gone = sorted(self._before - alive_now - self._alive)
            self._before = set()
            for key in gone:
                try:
                    self._callback(key, False)
                except Exception:  # the caller's: never let it stop the reopen
                    log.exception("liveliness callback for %s raised", key)


#: how long a reopen waits for the new session to say which tokens are alive
_RECONCILE_S = 1.0


def _reconcile(session: zenoh.Session, declared: list[_Declared]) -> None:
    """Every watcher asks the new session which tokens are alive (all at once), then tells its
    caller which it saw before and are gone."""
    asked: list[tuple[_Watcher, threading.Event, set[str]]] = []
    for item in declared:
        if isinstance(item, _Watcher):
            try:
                asked.append((item, *item.ask(session)))
            except zenoh.ZError as exc:
                log.debug("liveliness query on the new session failed: %s", zenoh_message(exc))
    deadline = time.monotonic() + _RECONCILE_S + 0.5
    for watcher, done, keys in asked:
        answered = done.wait(max(0.0, deadline - time.monotonic()))
        watcher.reconcile(set(keys) if answered else None)


#: (local, remote) address pair of a TCP connection
_Pair = tuple[tuple[str, int], tuple[str, int]]
_INET = (socket.AF_INET, socket.AF_INET6)


def _stream_links(session: zenoh.Session) -> set[_Pair]:
    """(local, remote) of the session's tcp/ and tls/ links now (none if it cannot say)."""
    pairs: set[_Pair] = set()
    try:
        links = session.info.links()
    except (zenoh.ZError, AttributeError) as exc:  # closed, or an older zenoh without links()
        log.debug("the session's links are not known: %s", exc)
        return pairs
    for link in links:
        src, dst = str(link.src), str(link.dst)
        if not src.startswith(("tcp/", "tls/")):
            continue
        local, remote = endpoint_address(src), endpoint_address(dst)
        if local is not None and remote is not None:
            pairs.add((local, remote))
    return pairs


def _abort_on_close(pairs: set[_Pair]) -> int:
    """Make the close of these TCP connections of this process abortive (``SO_LINGER`` on with
    a zero timeout: a reset, nothing waits): how many were found. Zenoh lingers up to 10 s on
    a closing tcp/tls link, in a blocking ``close`` that holds one of its runtime's threads;
    measured in the lab, a reopen after a dead zone then found the next ``zenoh.open`` stuck
    7.6 s instead of 1.5. The sockets are found in ``/proc/self/fd`` (Linux; elsewhere none)
    and changed through a duplicate of the descriptor; the connection is dead anyway."""
    if not pairs or not os.path.isdir("/proc/self/fd"):
        return 0
    found = 0
    for name in os.listdir("/proc/self/fd"):
        try:
            fd = int(name)
            if not stat.S_ISSOCK(os.fstat(fd).st_mode):
                continue
            with socket.socket(fileno=os.dup(fd)) as sock:
                if sock.type != socket.SOCK_STREAM or sock.family not in _INET:
                    continue  # a unix socket's name is a path, not an address
                local, remote = sock.getsockname()[:2], sock.getpeername()[:2]
                if ((str(local[0]), int(local[1])), (str(remote[0]), int(remote[1]))) in pairs:
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
                    found += 1
        except (OSError, ValueError):  # closed meanwhile, not connected, not ours to read
            continue
    return found


def _close_in_background(session: zenoh.Session) -> threading.Thread:
    """Close ``session`` on a thread of its own (started and returned): a link whose socket can
    send nothing must not hold the caller. Measured in the lab: a TCP session whose robot roamed
    took more than a second to close (its socket lingers), while zenoh 1.10 closed a TLS one
    stuck the same way at once; nothing promises either."""

    def close() -> None:
        try:
            session.close()  # type: ignore[no-untyped-call]
        except zenoh.ZError as exc:
            log.debug("closing the old session: %s", zenoh_message(exc))

    thread = threading.Thread(target=close, name="arpz-zenoh-close", daemon=True)
    thread.start()
    return thread


#: how long ``close`` waits for the sessions ``reopen`` left closing
_CLOSING_WAIT_S = 2.0


def _on_answer(link: _Link, key: str, on_reply: ReplyCallback) -> Callable[[zenoh.Reply], None]:
    """A request's reply callback for Zenoh: each reply's payload to ``on_reply``, counted as
    delivered; reply errors (Zenoh's "Timeout") left out."""

    def on_answer(reply: zenoh.Reply) -> None:
        sample = reply.ok
        if sample is None:
            return
        link.delivered += 1
        try:
            on_reply(sample.payload.to_bytes())
        except Exception:  # on Zenoh's network thread: log it, never let it reach Zenoh
            log.exception("reply handler for %s raised", key)

    return on_answer


class _ZenohResponder:
    """One query of ``serve_deferred``, held until finished (``arpz.core.transport.Responder``):
    dropping zenoh-python's ``Query`` is what tells the requester no more replies come."""

    def __init__(self, query: zenoh.Query, key: str, current: Callable[[], bool]) -> None:
        self._query: zenoh.Query | None = query
        self.key = key
        attachment = query.attachment
        self.attachment = attachment.to_bytes() if attachment is not None else None
        self._current = current
        self._lock = threading.Lock()

    def reply(self, payload: bytes, *, attachment: bytes | None = None) -> bool:
        with self._lock:
            query = self._query
            if query is None or not self._current():
                return False
            try:
                if attachment is None:
                    query.reply(self.key, payload)
                else:
                    query.reply(self.key, payload, attachment=attachment)
            except zenoh.ZError as exc:  # the requester left, or the session is closing
                log.debug("reply on %s failed: %s", self.key, zenoh_message(exc))
                return False
            return True

    def finish(self) -> None:
        with self._lock:
            query, self._query = self._query, None
        if query is not None:
            try:
                query.drop()  # type: ignore[no-untyped-call]
            except zenoh.ZError as exc:
                log.debug("finishing the query on %s failed: %s", self.key, zenoh_message(exc))


class ZenohTransport:
    """A Zenoh session behind the ``Transport`` protocol; ``reopen`` replaces the session in
    place (``arpz.core.transport.Reopenable``)."""

    def __init__(self, session: zenoh.Session, settings: SessionSettings) -> None:
        self._session = session
        self.settings = settings
        self._declared: list[_Declared] = []
        self._lock = threading.Lock()
        self._closed = False
        self._link = _Link()
        #: held by ``reopen`` and by every declaration: nothing is declared half-way through
        self._reopen_lock = threading.Lock()
        self._reopens = 0
        #: the threads closing the sessions ``reopen`` replaced
        self._closing: list[threading.Thread] = []
        #: the session's tcp/tls connections when it was opened (Zenoh may have dropped a
        #: dead one from its own list by the time it is replaced)
        self._links = _stream_links(session)

    @classmethod
    def open(cls, settings: SessionSettings, *, timeout_s: float = 0.0) -> ZenohTransport:
        """Open a session, retrying for ``timeout_s`` (a robot may start before its server)."""
        conf = build_config(settings)
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                return cls(zenoh.open(conf), settings)
            except zenoh.ZError as exc:
                if time.monotonic() >= deadline:
                    raise _open_error(settings, conf, exc, timeout_s) from exc
                time.sleep(0.1)
                conf = build_config(settings)

    @property
    def fragment_bytes(self) -> int:
        """The fragment size of this session's links (``arpz.core.link_sizes``): a ``Writer`` on
        this transport sends a larger sample as fragments of this size (a UDP datagram's worth
        over UDP, most of a Zenoh batch over a stream link)."""
        endpoints = self.settings.connect or self.settings.listen
        return link_sizes(list(endpoints)).fragment_bytes

    @property
    def zid(self) -> str:
        return str(self._session.info.zid())

    @property
    def reopens(self) -> int:
        return self._reopens

    @property
    def delivered(self) -> int:
        """Samples, liveliness changes and replies this transport handed to callbacks so far
        (the callback subscribers', watchers' and requests'; a pull subscriber's samples are
        not counted, to keep the ingest path as it was): on a robot, what it heard from the
        CEDDP, a reliable channel's ACKNACKs and heartbeats among it."""
        return self._link.delivered

    @property
    def down(self) -> bool:
        """The session is being replaced (``reopen`` closed it and no new one is open yet)."""
        return self._link.down

    def _adopt(self, handle: _Declared, what: str) -> None:
        """Declare ``handle`` on the session and keep it for ``close`` and ``reopen``. While
        the transport is down it is only kept: the next session declares it."""
        with self._reopen_lock:
            if not self._link.down:
                with _translated(what):
                    handle.attach(self._session)
            with self._lock:
                self._declared.append(handle)

    def publisher(
        self, key: str, *, express: bool = False, block: bool = True, bulk: bool = False
    ) -> Publisher:
        congestion = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        priority = zenoh.Priority.DATA_LOW if bulk else zenoh.Priority.DATA

        def declare(session: zenoh.Session, _current: Callable[[], bool]) -> Any:
            return session.declare_publisher(
                key, congestion_control=congestion, express=express, priority=priority
            )

        pub = _ZenohPublisher(declare, self._link)
        self._adopt(pub, f"declare a publisher on {key}")
        return pub

    def put(
        self, key: str, payload: bytes, *, attachment: bytes | None = None, bulk: bool = False
    ) -> None:
        """Through the session, not a publisher kept per key: a kept publisher's put costs
        0.56-0.85x of this one (``python benchmarks/investigations/zenoh_put.py``), but with it the
        downlink
        over a lossy UDP link failed its test (tests/integration/test_downlink.py;
        benchmarks/investigations/README.md, stop 27)."""
        try:  # not ``_translated``: once per ACKNACK on the CEDDP's sensor path
            if bulk:
                self._session.put(
                    key, payload, attachment=attachment, priority=zenoh.Priority.DATA_LOW
                )
            elif attachment is None:
                self._session.put(key, payload)
            else:
                self._session.put(key, payload, attachment=attachment)
        except zenoh.ZError as exc:
            if self._link.down and not self._closed:
                return  # dropped, as on a congested link
            raise TransportError(f"put on {key}: {zenoh_message(exc)}") from exc

    def subscribe(self, key_expr: str, callback: DataCallback) -> Handle:
        expr, keep = bundle.subscription(key_expr)
        link = self._link

        def declare(session: zenoh.Session, current: Callable[[], bool]) -> Any:
            def on_sample(sample: zenoh.Sample) -> None:
                if not current():
                    return
                link.delivered += 1
                att = sample.attachment
                key = str(sample.key_expr)
                payload = sample.payload.to_bytes()
                attachment = att.to_bytes() if att is not None else None
                if keep is None and not key.endswith(bundle.CHUNK):
                    callback(key, payload, attachment)
                    return
                for item in bundle.expand(key, payload, attachment, keep):
                    callback(*item)

            return session.declare_subscriber(expr, on_sample)

        handle = _Declared(declare)
        self._adopt(handle, f"subscribe to {key_expr}")
        return handle

    def subscribe_pull(self, key_expr: str, capacity: int) -> PullSubscriber:
        expr, keep = bundle.subscription(key_expr)

        def declare(session: zenoh.Session, _current: Callable[[], bool]) -> Any:
            return session.declare_subscriber(expr, zenoh.handlers.FifoChannel(capacity))

        handle = _ZenohPullSubscriber(declare, keep, self._link)
        self._adopt(handle, f"subscribe to {key_expr}")
        return handle

    def declare_token(self, key: str) -> Handle:
        def declare(session: zenoh.Session, _current: Callable[[], bool]) -> Any:
            return session.liveliness().declare_token(key)

        handle = _Declared(declare)
        self._adopt(handle, f"declare the liveliness token {key}")
        return handle

    def watch_liveliness(self, key_expr: str, callback: LivelinessCallback) -> Handle:
        handle = _Watcher(key_expr, callback, self._link)
        self._adopt(handle, f"watch liveliness on {key_expr}")
        return handle

    def serve(self, key: str, handler: QueryHandler) -> Handle:
        """A queryable that replies from Zenoh's callback thread: the handler only stamps and
        encodes, and a reply is one small non-blocking send (DROP congestion control: a full
        queue loses the reply, which the requester sees as a timeout). Handing the query to a
        worker would add a thread wake-up to the request's path only, an asymmetry that a
        clock exchange would take for offset."""

        def declare(session: zenoh.Session, current: Callable[[], bool]) -> Any:
            def on_query(query: zenoh.Query) -> None:
                if not current():
                    return
                payload = query.payload
                try:
                    answer = handler(payload.to_bytes() if payload is not None else b"")
                    if answer is not None:
                        query.reply(key, answer, express=True)
                except zenoh.ZError as exc:  # the requester left, or the session is closing
                    log.debug("reply on %s failed: %s", key, zenoh_message(exc))

            return session.declare_queryable(key, on_query, complete=True)

        handle = _Declared(declare)
        self._adopt(handle, f"serve {key}")
        return handle

    def request(
        self, key: str, payload: bytes, on_reply: ReplyCallback, *, timeout_s: float
    ) -> None:
        on_answer = _on_answer(self._link, key, on_reply)
        # Run on Zenoh's network thread (indirect=False), not on a Python thread zenoh-python
        # would start for every request: ``get`` returns only once that thread holds the GIL,
        # and a robot's clock bursts (4 requests every 2 s) stalled its sensing loop by that
        # much. ``python benchmarks/investigations/request_cost.py``: 505 against 161 us in the
        # call; with 300
        # busy threads beside (a fleet worker has 770), 2 034 against 643 us
        try:
            self._session.get(
                key,
                zenoh.handlers.Callback(on_answer, indirect=False),
                payload=payload,
                timeout=timeout_s,
                express=True,
                congestion_control=zenoh.CongestionControl.DROP,
            )
        except zenoh.ZError as exc:
            if self._link.down and not self._closed:
                return  # dropped: the requester sees no reply, as after a congested link
            raise TransportError(f"request on {key}: {zenoh_message(exc)}") from exc

    def serve_deferred(self, key_expr: str, handler: DeferredQueryHandler) -> Handle:
        """A queryable whose queries are answered through a ``Responder`` (``arpz.core.
        transport.DeferredQueries``): the handler runs on zenoh-python's queryable thread and
        returns at once; the query stays open (the requester waits) until the responder
        finishes it or the requester's timeout passes. Each reply goes on the query's own key
        (a queryable of ``srv/*`` asked for ``srv/dock`` replies on ``srv/dock``)."""

        def declare(session: zenoh.Session, current: Callable[[], bool]) -> Any:
            def on_query(query: zenoh.Query) -> None:
                if not current():
                    return
                payload = query.payload
                responder = _ZenohResponder(query, str(query.key_expr), current)
                try:
                    handler(
                        responder.key, payload.to_bytes() if payload is not None else b"", responder
                    )
                except Exception:  # on Zenoh's thread: log it, never let it reach Zenoh
                    log.exception("query handler for %s raised", key_expr)
                    responder.finish()

            return session.declare_queryable(key_expr, on_query, complete=True)

        handle = _Declared(declare)
        self._adopt(handle, f"serve {key_expr}")
        return handle

    def query(
        self,
        key: str,
        payload: bytes,
        on_reply: ReplyCallback,
        on_done: DoneCallback,
        *,
        timeout_s: float,
    ) -> None:
        """``DeferredQueries.query``: no consolidation (each reply is handed on as it comes,
        an acknowledgement before the answer), replies and the end on Zenoh's network thread
        (as ``request``); a reply error (Zenoh's "Timeout") only precedes the end."""
        on_answer = _on_answer(self._link, key, on_reply)

        def on_end() -> None:
            try:
                on_done()
            except Exception:
                log.exception("end-of-query handler for %s raised", key)

        if self._link.down or self._closed:
            state = "closed" if self._closed else "down (being replaced)"
            raise TransportError(f"query on {key}: the session is {state}")
        with _translated(f"query on {key}"):
            self._session.get(
                key,
                zenoh.handlers.Callback(on_answer, on_end, indirect=False),
                payload=payload,
                timeout=timeout_s,
                consolidation=zenoh.ConsolidationMode.NONE,
                congestion_control=zenoh.CongestionControl.DROP,
            )

    def reopen(self) -> None:
        """Replace the session (``arpz.core.transport.Reopenable``): close it on a thread of its own
        (never waited for: a dead link may hold it), open a new one with the same settings (one
        connection attempt per endpoint, each bounded by ``transport/unicast/open_timeout``)
        and declare everything on it again. Raises ``TransportError`` when the new session
        cannot be opened: the transport stays down, and the next call only tries to open one."""
        with self._reopen_lock:
            if self._closed:
                raise TransportError("reopen: the transport is closed")
            if not self._link.down:
                self._link.down = True
                with self._lock:
                    declared = list(self._declared)
                for item in declared:
                    item.detach()  # a receiver blocked on the old session is let go now
                aborted = _abort_on_close(self._links | _stream_links(self._session))
                if aborted:
                    log.debug(
                        "closing %d tcp/tls connection(s) of the old session by reset", aborted
                    )
                self._closing.append(_close_in_background(self._session))
            self._closing = [thread for thread in self._closing if thread.is_alive()]
            conf = build_config(self.settings)
            started = time.monotonic()
            try:
                session = zenoh.open(conf)
            except zenoh.ZError as exc:
                raise _open_error(self.settings, conf, exc, 0.0) from exc
            opened = time.monotonic()
            with self._lock:
                closed = self._closed
                if not closed:
                    self._session = session
                    self._links = _stream_links(session)
                declared = list(self._declared)
            if closed:  # closed while the new session was being opened
                _close_in_background(session).join(_CLOSING_WAIT_S)
                raise TransportError("reopen: the transport was closed meanwhile")
            try:
                for item in declared:
                    item.attach(session)
                attached = time.monotonic()
                _reconcile(session, declared)
            except zenoh.ZError as exc:  # the new session died under us: down, try again
                for item in declared:
                    item.detach()
                self._closing.append(_close_in_background(session))
                raise TransportError(
                    f"reopen: declaring on the new session failed: {zenoh_message(exc)}"
                ) from exc
            self._link.down = False
            self._reopens += 1
            log.debug(
                "session reopened: opened in %.3f s, %d declarations in %.3f s, liveliness "
                "reconciled in %.3f s",
                opened - started,
                len(declared),
                attached - opened,
                time.monotonic() - attached,
            )

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            declared, self._declared = self._declared, []
            session = self._session
        for item in reversed(declared):
            item.undeclare()
        try:
            session.close()  # type: ignore[no-untyped-call]
        except zenoh.ZError as exc:
            log.debug("session close: %s", exc)
        deadline = time.monotonic() + _CLOSING_WAIT_S
        for thread in self._closing:  # a process must not exit in the middle of a close
            thread.join(max(0.0, deadline - time.monotonic()))

    def __enter__(self) -> ZenohTransport:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _open_error(
    settings: SessionSettings, conf: zenoh.Config, exc: zenoh.ZError, timeout_s: float
) -> TransportError:
    """Why a session could not be opened, naming the endpoints (and the TLS identity)."""
    where = ", ".join(settings.connect or settings.listen) or "(no endpoint)"
    tried = f" for {timeout_s:g} s" if timeout_s else ""
    endpoints = [*settings.connect, *settings.listen]
    identity = (
        f" ({tls_identity(conf)})"
        if any(e.startswith(("tls/", "quic/")) for e in endpoints)
        else ""
    )
    return TransportError(
        f"cannot open a Zenoh {settings.mode} session on {where}{identity}, "
        f"tried{tried or ' once'}: {zenoh_message(exc)}"
    )
