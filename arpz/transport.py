"""The Zenoh seam: the only module of arpz that imports zenoh.

Everything above it (robot agent, CEDDP, reliable channel) talks to the ``Transport`` protocol:
put bytes on a key, subscribe to a key expression with a callback, declare and watch liveliness
tokens. ``ZenohTransport`` is the real thing; ``arpz.memory_transport.MemoryTransport`` is an
in-process fake with the same contract for fast, deterministic unit tests.

Contract for callbacks: they run on a transport-owned thread and must not block or call back into
the transport for long; hand the data to a queue and let a worker do the work (zenoh-python's own
advice). Every session is closed on every exit path: a Python process that exits with a declared
callback subscriber hangs (see shared notes).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import zenoh

log = logging.getLogger(__name__)

#: (key, payload, attachment) -> None
DataCallback = Callable[[str, bytes, bytes | None], None]
#: (key, alive) -> None
LivelinessCallback = Callable[[str, bool], None]


class Publisher(Protocol):
    def put(self, payload: bytes, *, attachment: bytes | None = None) -> None: ...
    def undeclare(self) -> None: ...

    @property
    def matching(self) -> bool:
        """Some subscriber (anywhere in the router mesh) matches this key right now."""
        ...


class Handle(Protocol):
    """Something declared that must be undeclared (subscriber, token, liveliness subscriber)."""

    def undeclare(self) -> None: ...


#: (key, payload, attachment)
Received = tuple[str, bytes, bytes | None]


class PullSubscriber(Protocol):
    """A subscriber whose samples wait in a bounded queue owned by the transport.

    When the queue is full the transport stops reading the link (backpressure to the publishers,
    which block with congestion control BLOCK): samples are delayed, never dropped. Only one
    thread may receive. ``recv`` blocks; ``undeclare()`` makes it raise once the queue is empty
    (a receiving thread ends that way), or wake it by putting a sample on a matching key.
    """

    def try_recv(self) -> Received | None: ...
    def recv(self) -> Received: ...
    def undeclare(self) -> None: ...


class Transport(Protocol):
    def publisher(self, key: str, *, express: bool = False, block: bool = True) -> Publisher: ...
    def put(self, key: str, payload: bytes, *, attachment: bytes | None = None) -> None: ...
    def subscribe(self, key_expr: str, callback: DataCallback) -> Handle: ...
    def subscribe_pull(self, key_expr: str, capacity: int) -> PullSubscriber: ...
    def declare_token(self, key: str) -> Handle: ...
    def watch_liveliness(self, key_expr: str, callback: LivelinessCallback) -> Handle: ...
    def close(self) -> None: ...


class TransportError(RuntimeError):
    """The Zenoh session could not be opened or used; the message says which endpoint and why."""


@dataclass(frozen=True)
class SessionSettings:
    """How to open a Zenoh session. Multicast scouting is off unless asked for: on WiFi it is
    discovery traffic nobody needs when the router's address is known, and tests must not see
    each other."""

    mode: str = "client"
    listen: Sequence[str] = ()
    connect: Sequence[str] = ()
    multicast_scouting: bool = False
    #: extra Zenoh config entries, key path -> JSON value (for TLS, access control, timeouts)
    extra: dict[str, object] = field(default_factory=dict)
    #: a Zenoh JSON5 config file loaded first; the settings above are applied on top of it
    config_file: str | None = None


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
        raise TransportError(f"invalid Zenoh configuration: {exc}") from exc
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
        if attachment is None:
            self._inner.put(payload)
        else:
            self._inner.put(payload, attachment=attachment)

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
    def __init__(self, inner: zenoh.Subscriber) -> None:  # type: ignore[type-arg]
        super().__init__(inner)
        # the handler's own methods, not the subscriber's: a thread blocked in the subscriber's
        # recv keeps it borrowed and undeclare fails ("Already borrowed"); blocked in the
        # handler's, undeclare closes the channel and that recv raises ZError
        self._try_recv = inner.handler.try_recv
        self._recv = inner.handler.recv

    @staticmethod
    def _received(sample: zenoh.Sample) -> Received:
        att = sample.attachment
        return (
            str(sample.key_expr),
            sample.payload.to_bytes(),
            att.to_bytes() if att is not None else None,
        )

    def try_recv(self) -> Received | None:
        sample = self._try_recv()
        return None if sample is None else self._received(sample)

    def recv(self) -> Received:
        return self._received(self._recv())


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
                    raise TransportError(
                        f"cannot open a Zenoh {settings.mode} session on {where}: {exc}"
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
        pub = _ZenohPublisher(
            self._session.declare_publisher(key, congestion_control=congestion, express=express)
        )
        self._keep(pub)
        return pub

    def put(self, key: str, payload: bytes, *, attachment: bytes | None = None) -> None:
        if attachment is None:
            self._session.put(key, payload)
        else:
            self._session.put(key, payload, attachment=attachment)

    def subscribe(self, key_expr: str, callback: DataCallback) -> Handle:
        def on_sample(sample: zenoh.Sample) -> None:
            att = sample.attachment
            callback(
                str(sample.key_expr),
                sample.payload.to_bytes(),
                att.to_bytes() if att is not None else None,
            )

        handle = _Declared(self._session.declare_subscriber(key_expr, on_sample))
        self._keep(handle)
        return handle

    def subscribe_pull(self, key_expr: str, capacity: int) -> PullSubscriber:
        handle = _ZenohPullSubscriber(
            self._session.declare_subscriber(key_expr, zenoh.handlers.FifoChannel(capacity))
        )
        self._keep(handle)
        return handle

    def declare_token(self, key: str) -> Handle:
        handle = _Declared(self._session.liveliness().declare_token(key))
        self._keep(handle)
        return handle

    def watch_liveliness(self, key_expr: str, callback: LivelinessCallback) -> Handle:
        def on_change(sample: zenoh.Sample) -> None:
            callback(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)

        handle = _Declared(
            self._session.liveliness().declare_subscriber(key_expr, on_change, history=True)
        )
        self._keep(handle)
        return handle

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
