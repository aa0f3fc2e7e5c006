"""The Zenoh seam: the only module of arpz's runtime that imports zenoh.

``ZenohTransport`` implements ``arpz.transport.Transport`` over a Zenoh session, and every
Zenoh error that crosses the seam comes out as ``TransportError`` (or ``ConfigError`` for a
configuration Zenoh refuses), so callers never need ``except Exception``. The rest of the module
reads Zenoh JSON5 configs into sentences that name the file and the field.
"""

from __future__ import annotations

import collections
import contextlib
import json
import logging
import re
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import zenoh

from arpz.endpoints import check_endpoints
from arpz.errors import ConfigError
from arpz.protocol import bundle
from arpz.transport import (
    DataCallback,
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
        for key, value in settings.extra.items():
            conf.insert_json5(key, json.dumps(value))
    except zenoh.ZError as exc:
        raise TransportError(f"invalid Zenoh configuration: {zenoh_message(exc)}") from exc
    return conf


class _Declared:
    def __init__(self, inner: object) -> None:
        self._inner = inner
        self._lock = threading.Lock()
        self._done = False

    def undeclare(self) -> None:
        with self._lock:
            if self._done:
                return
            self._done = True
        try:
            self._inner.undeclare()  # type: ignore[attr-defined]
        except (zenoh.ZError, RuntimeError) as exc:  # closed session, or a receiver still blocked
            log.debug("undeclare failed: %s", exc)


class _ZenohPublisher:
    def __init__(self, inner: zenoh.Publisher) -> None:
        self._inner = inner

    def put(self, payload: bytes, *, attachment: bytes | None = None) -> None:
        try:  # not ``_translated``: once per sample on a robot's hot path
            if attachment is None:
                self._inner.put(payload)
            else:
                self._inner.put(payload, attachment=attachment)
        except zenoh.ZError as exc:
            raise TransportError(f"put: {zenoh_message(exc)}") from exc

    @property
    def matching(self) -> bool:
        try:
            status = self._inner.matching_status
        except zenoh.ZError as exc:  # closed session
            log.debug("matching status after close: %s", exc)
            return False
        # the stubs say bool; zenoh-python 1.x returns a MatchingStatus with ``.matching``
        return bool(getattr(status, "matching", status))

    def undeclare(self) -> None:
        try:
            self._inner.undeclare()  # type: ignore[no-untyped-call]
        except zenoh.ZError as exc:
            log.debug("undeclare after close: %s", exc)


class _ZenohPullSubscriber(_Declared):
    def __init__(
        self,
        inner: zenoh.Subscriber,  # type: ignore[type-arg]
        keep: Callable[[str], bool] | None,
    ) -> None:
        super().__init__(inner)
        # the handler's own methods, not the subscriber's: a thread blocked in the subscriber's
        # recv keeps it borrowed and undeclare fails ("Already borrowed"); blocked in the
        # handler's, undeclare closes the channel and that recv raises ZError
        self._try_recv = inner.handler.try_recv
        self._recv = inner.handler.recv
        #: a widened subscription's filter (``bundle.subscription``)
        self._keep = keep
        #: a bundle's entries not yet received (one receiving thread, so no lock)
        self._pending: collections.deque[Received] = collections.deque()
        #: the Zenoh sample last taken from the FIFO: its timestamp, read only when asked
        self._last: zenoh.Sample | None = None

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

    # try/except rather than ``_translated``: this runs once per sample on the ingest path, and
    # a generator context manager costs more than the rest of the call
    def _next(self, get: Callable[[], zenoh.Sample | None]) -> Received | None:
        if self._pending:
            return self._pending.popleft()
        while True:
            try:
                sample = get()
            except zenoh.ZError as exc:
                raise TransportError(f"receive: {zenoh_message(exc)}") from exc
            if sample is None:
                return None
            self._last = sample
            item = self._received(sample)
            if item is not None:
                return item

    def try_recv(self) -> Received | None:
        return self._next(self._try_recv)

    def recv(self) -> Received:
        """Blocks; raises ``TransportError`` once the subscriber is undeclared and drained."""
        item = self._next(self._recv)
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


class ZenohTransport:
    """A Zenoh session behind the ``Transport`` protocol."""

    def __init__(self, session: zenoh.Session, settings: SessionSettings) -> None:
        self._session = session
        self.settings = settings
        self._declared: list[_Declared | _ZenohPublisher] = []
        self._lock = threading.Lock()
        self._closed = False

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
                    where = ", ".join(settings.connect or settings.listen) or "(no endpoint)"
                    tried = f" for {timeout_s:g} s" if timeout_s else ""
                    endpoints = [*settings.connect, *settings.listen]
                    identity = (
                        f" ({tls_identity(conf)})"
                        if any(e.startswith(("tls/", "quic/")) for e in endpoints)
                        else ""
                    )
                    raise TransportError(
                        f"cannot open a Zenoh {settings.mode} session on {where}{identity}, "
                        f"tried{tried or ' once'}: {zenoh_message(exc)}"
                    ) from exc
                time.sleep(0.1)
                conf = build_config(settings)

    @property
    def zid(self) -> str:
        return str(self._session.info.zid())

    def _keep(self, item: _Declared | _ZenohPublisher) -> None:
        with self._lock:
            self._declared.append(item)

    def publisher(self, key: str, *, express: bool = False, block: bool = True) -> Publisher:
        congestion = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        with _translated(f"declare a publisher on {key}"):
            inner = self._session.declare_publisher(
                key, congestion_control=congestion, express=express
            )
        pub = _ZenohPublisher(inner)
        self._keep(pub)
        return pub

    def put(self, key: str, payload: bytes, *, attachment: bytes | None = None) -> None:
        """Through the session, not a publisher kept per key: a kept publisher's put costs
        0.56-0.85x of this one (``python benchmarks/zenoh_put.py``), but with it the downlink
        over a lossy UDP link failed its test (tests/integration/test_downlink.py;
        benchmarks/RESULTS.md, stop 27)."""
        try:  # not ``_translated``: once per ACKNACK on the CEDDP's sensor path
            if attachment is None:
                self._session.put(key, payload)
            else:
                self._session.put(key, payload, attachment=attachment)
        except zenoh.ZError as exc:
            raise TransportError(f"put on {key}: {zenoh_message(exc)}") from exc

    def subscribe(self, key_expr: str, callback: DataCallback) -> Handle:
        expr, keep = bundle.subscription(key_expr)

        def on_sample(sample: zenoh.Sample) -> None:
            att = sample.attachment
            key = str(sample.key_expr)
            payload = sample.payload.to_bytes()
            attachment = att.to_bytes() if att is not None else None
            if keep is None and not key.endswith(bundle.CHUNK):
                callback(key, payload, attachment)
                return
            for item in bundle.expand(key, payload, attachment, keep):
                callback(*item)

        with _translated(f"subscribe to {key_expr}"):
            handle = _Declared(self._session.declare_subscriber(expr, on_sample))
        self._keep(handle)
        return handle

    def subscribe_pull(self, key_expr: str, capacity: int) -> PullSubscriber:
        expr, keep = bundle.subscription(key_expr)
        with _translated(f"subscribe to {key_expr}"):
            inner = self._session.declare_subscriber(expr, zenoh.handlers.FifoChannel(capacity))
        handle = _ZenohPullSubscriber(inner, keep)
        self._keep(handle)
        return handle

    def declare_token(self, key: str) -> Handle:
        with _translated(f"declare the liveliness token {key}"):
            handle = _Declared(self._session.liveliness().declare_token(key))
        self._keep(handle)
        return handle

    def watch_liveliness(self, key_expr: str, callback: LivelinessCallback) -> Handle:
        def on_change(sample: zenoh.Sample) -> None:
            callback(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)

        with _translated(f"watch liveliness on {key_expr}"):
            inner = self._session.liveliness().declare_subscriber(key_expr, on_change, history=True)
        handle = _Declared(inner)
        self._keep(handle)
        return handle

    def serve(self, key: str, handler: QueryHandler) -> Handle:
        """A queryable that replies from Zenoh's callback thread: the handler only stamps and
        encodes, and a reply is one small non-blocking send (DROP congestion control: a full
        queue loses the reply, which the requester sees as a timeout). Handing the query to a
        worker would add a thread wake-up to the request's path only, an asymmetry that a
        clock exchange would take for offset."""

        def on_query(query: zenoh.Query) -> None:
            payload = query.payload
            try:
                answer = handler(payload.to_bytes() if payload is not None else b"")
                if answer is not None:
                    query.reply(key, answer, express=True)
            except zenoh.ZError as exc:  # the requester left, or the session is closing
                log.debug("reply on %s failed: %s", key, zenoh_message(exc))

        with _translated(f"serve {key}"):
            handle = _Declared(self._session.declare_queryable(key, on_query, complete=True))
        self._keep(handle)
        return handle

    def request(
        self, key: str, payload: bytes, on_reply: ReplyCallback, *, timeout_s: float
    ) -> None:
        def on_answer(reply: zenoh.Reply) -> None:
            sample = reply.ok
            if sample is None:
                return
            try:
                on_reply(sample.payload.to_bytes())
            except Exception:  # on Zenoh's network thread: log it, never let it reach Zenoh
                log.exception("reply handler for %s raised", key)

        # Run on Zenoh's network thread (indirect=False), not on a Python thread zenoh-python
        # would start for every request: ``get`` returns only once that thread holds the GIL,
        # and a robot's clock bursts (4 requests every 2 s) stalled its sensing loop by that
        # much. ``python benchmarks/request_cost.py``: 505 against 161 us in the call; with 300
        # busy threads beside (a fleet worker has 770), 2 034 against 643 us
        with _translated(f"request on {key}"):
            self._session.get(
                key,
                zenoh.handlers.Callback(on_answer, indirect=False),
                payload=payload,
                timeout=timeout_s,
                express=True,
                congestion_control=zenoh.CongestionControl.DROP,
            )

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            declared, self._declared = self._declared, []
        for item in reversed(declared):
            item.undeclare()
        try:
            self._session.close()  # type: ignore[no-untyped-call]
        except zenoh.ZError as exc:
            log.debug("session close: %s", exc)

    def __enter__(self) -> ZenohTransport:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
