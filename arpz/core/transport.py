"""The transport contract: what arpz needs from a pub/sub bus, with no Zenoh in it.

Everything above it (robot agent, CEDDP, reliable channel) talks to the ``Transport`` protocol:
put bytes on a key, subscribe to a key expression with a callback, declare and watch liveliness
tokens. ``arpz.transport.zenoh.ZenohTransport`` is the real thing (the only module of the
runtime that imports zenoh); ``arpz.transport.memory.MemoryTransport`` is an in-process fake with
the same contract for fast, deterministic unit tests.

Contract for callbacks: they run on a transport-owned thread and must not block or call back into
the transport for long; hand the data to a queue and let a worker do the work (zenoh-python's own
advice). Every session is closed on every exit path: a Python process that exits with a declared
callback subscriber hangs (see shared notes).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

from arpz.core.errors import ArpzError

#: (key, payload, attachment) -> None
DataCallback = Callable[[str, bytes, bytes | None], None]
#: (key, alive) -> None
LivelinessCallback = Callable[[str, bool], None]
#: (request payload) -> reply payload (None: no reply), for ``serve``: it runs on a
#: transport-owned thread and must return at once (compute and encode, nothing that waits)
QueryHandler = Callable[[bytes], bytes | None]
#: (reply payload) -> None, for ``request``: on a transport-owned thread, only record or queue
ReplyCallback = Callable[[bytes], None]
#: () -> None, for ``query``: the request is over (every replier finished, or its timeout
#: passed, or nobody serves the key); called once, on a transport-owned thread
DoneCallback = Callable[[], None]


class Publisher(Protocol):
    def put(self, payload: bytes, *, attachment: bytes | None = None) -> None: ...
    def undeclare(self) -> None: ...

    @property
    def matching(self) -> bool:
        """Some subscriber (anywhere in the router mesh) matches this key right now."""
        ...


@runtime_checkable
class HoldingPublisher(Publisher, Protocol):
    """A publisher that may hold a message back until the calling thread's tick ends (a
    robot's bundle, ``arpz.channel.bundling``). A reliable writer must not announce a held seq in a
    heartbeat, or the reader NACKs data that is merely late: it asks ``will_hold`` before the
    put, and the publisher calls ``on_released`` once the bundle left (or was refused)."""

    on_released: Callable[[], None] | None

    def will_hold(self, payload: bytes, attachment: bytes | None) -> bool:
        """Whether ``put`` of this message on the calling thread holds it until the tick ends."""
        ...

    def release_held(self) -> None:
        """Send what the calling thread holds now (a writer about to wait for
        acknowledgements of messages that may be among it)."""
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

    def waited_ns(self) -> int | None:
        """How long the message last taken had waited since it reached this session, ns (None:
        not known). A receiver that falls behind reads its backlog here, in time: the queue's
        depth is the transport's, and Zenoh's FIFO does not tell it."""
        ...


class Transport(Protocol):
    def publisher(
        self, key: str, *, express: bool = False, block: bool = True, bulk: bool = False
    ) -> Publisher:
        """``bulk``: the key's messages yield to every other message of the session on a busy
        link (Zenoh priority DATA_LOW): a camera's frames, so that a saturated link still
        carries the robot's small sensors, reports and clock exchanges first (issue 39)."""
        ...

    def put(
        self, key: str, payload: bytes, *, attachment: bytes | None = None, bulk: bool = False
    ) -> None: ...
    def subscribe(self, key_expr: str, callback: DataCallback) -> Handle: ...
    def subscribe_pull(self, key_expr: str, capacity: int) -> PullSubscriber: ...
    def declare_token(self, key: str) -> Handle: ...
    def watch_liveliness(self, key_expr: str, callback: LivelinessCallback) -> Handle: ...
    def serve(self, key: str, handler: QueryHandler) -> Handle:
        """Answer every request on ``key`` with ``handler(payload)`` (a Zenoh queryable)."""
        ...

    def request(
        self, key: str, payload: bytes, on_reply: ReplyCallback, *, timeout_s: float
    ) -> None:
        """Send a request to whoever serves ``key`` and return at once; each reply that comes
        within ``timeout_s`` is handed to ``on_reply`` (none: nobody served it in time, or the
        request was dropped on a congested link: requests never block, so callers that need an
        answer ask again, as the clock sync does every period).
        ``on_reply`` may run on the transport's network thread: it must be quick and never
        block (decode, count, take a short lock)."""
        ...

    def close(self) -> None: ...


class Responder(Protocol):
    """One request taken by a ``serve_deferred`` handler, answered when the answer is ready:
    ``reply`` any number of times, from any thread, then ``finish``. A request left unfinished
    ends at the requester's timeout."""

    #: the request's attachment (None: it had none; the in-memory bus carries none): the ROS 2
    #: bridge reads rmw_zenoh's service request header from it (docs/ros2.md "Services")
    attachment: bytes | None

    def reply(self, payload: bytes, *, attachment: bytes | None = None) -> bool:
        """Send one reply, with ``attachment`` if given (the in-memory bus drops it); False
        when it could not be sent (after ``finish``, or the session closed or was replaced).
        True does not say the requester got it: one whose timeout passed drops it (Zenoh's
        queryable side does not know; the in-memory bus does, and says False)."""
        ...

    def finish(self) -> None:
        """No more replies: the requester's request is over once every replier finished.
        Idempotent; replies after it are dropped."""
        ...


#: (key, request payload, responder) -> None, for ``serve_deferred``: on a transport-owned
#: thread, so it must return at once: reply at once, or hand the responder to a worker
DeferredQueryHandler = Callable[[str, bytes, Responder], None]


@runtime_checkable
class DeferredQueries(Protocol):
    """A transport whose queryables may answer later, from another thread (a robot's services,
    ``arpz.robot.services``), and whose requester learns when a request is over
    (``ZenohTransport`` and ``MemoryTransport``). Beside ``Transport``'s ``serve`` /
    ``request``, whose handler answers inside the transport's callback and whose requester
    sees only replies."""

    def serve_deferred(self, key_expr: str, handler: DeferredQueryHandler) -> Handle:
        """Hand every request on a key matching ``key_expr`` to ``handler`` with its own
        ``Responder`` (a Zenoh queryable whose queries are finished by the responder)."""
        ...

    def query(
        self,
        key: str,
        payload: bytes,
        on_reply: ReplyCallback,
        on_done: DoneCallback,
        *,
        timeout_s: float,
    ) -> None:
        """Send a request to whoever serves ``key`` and return at once; every reply is handed to
        ``on_reply`` as it comes (none held back for consolidation), then ``on_done`` once:
        when every replier finished, at ``timeout_s``, or at once when no queryable the
        session can see serves ``key`` (nobody does, or access control hides it). Both run on
        a transport-owned thread: quick, never blocking. Raises ``TransportError`` when the
        session is closed or down (being replaced), and then calls neither."""
        ...


@runtime_checkable
class Reopenable(Protocol):
    """A transport that can replace its session in place (``ZenohTransport``, and
    ``MemoryTransport`` for tests): what a robot does when its link to the CEDDP died and the
    session did not come back by itself (docs/operations.md, "Drops and reconnection").

    ``reopen`` closes the session (on a thread of its own: a dead link may hold the close) and
    opens a new one with the same settings, then declares again everything handed out: the
    publishers, subscribers, pull subscribers, tokens, liveliness watchers and queryables given
    to callers keep working (the same objects). A liveliness watcher sees the tokens alive in
    the new session again (history: ``alive`` once more for those it knew), and is told that
    those it saw alive and that are gone vanished; a token alive throughout never vanishes (a
    reliable writer keeps its reader's state across the reopen). While the
    transport is down (from the close until a new session is open) puts and requests are
    dropped as a congested link drops them, and pull subscribers wait. Raises
    ``TransportError`` when no new session could be opened (the transport stays down: call
    again later)."""

    def reopen(self) -> None: ...

    @property
    def reopens(self) -> int:
        """Sessions opened by ``reopen`` so far."""
        ...

    @property
    def delivered(self) -> int:
        """What the transport handed to callbacks so far (samples of callback subscribers,
        liveliness changes, replies): grows while anything is heard from the other side."""
        ...


class TransportError(ArpzError, RuntimeError):
    """The session could not be opened or used (Zenoh's own errors are translated into this at
    the seam); the message says which endpoint and why."""


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
    #: Zenoh config entries applied only where ``config_file`` leaves Zenoh's default (a robot's
    #: link timing: ``CLIENT_LINK_DEFAULTS``); ``extra`` always applies
    defaults: Mapping[str, object] = field(default_factory=dict)


#: A robot's Zenoh link timing (issue 39, measured in the namespace lab: docs/deploy.md, "Link
#: timing"). A connection attempt gives up after ``open_timeout``: Zenoh's 10 s let a UDP or
#: QUIC handshake lost in a dead zone hold the next attempt back for 10 s; 1.5 s leaves room
#: for one resend of a lost TCP SYN or QUIC Initial (both after 1 s) inside the attempt, which a
#: timeout of 1 s cut off, and a QUIC router then stalled on the abandoned handshake. Zenoh
#: retries a lost router every 0.25-0.5 s instead of 1-4 s. The lease stays Zenoh's (10 s,
#: keep-alive every 2.5 s): it is what the router waits before it drops a silent robot, and the
#: robot does not rely on it to notice a dead link (``arpz.robot.link_monitor``). A
#: ``zenoh_config`` file that sets any of these keeps its own value.
#:
#: A TCP link's kernel send buffer is held to 64 KiB (``so_sndbuf`` 32 KiB, which the kernel
#: doubles): Zenoh's priorities order only what has not reached the socket yet, and the
#: kernel's own buffer (megabytes once it autotunes) queues camera frames ahead of every small
#: sample on a saturated link. In the lab with a 5 Hz camera of 921 600-byte frames
#: (``python -m pytest -n 0 -s tests/integration/test_lab_bandwidth.py``), the IMU's p99 with
#: the frames on their own thread: at 20 Mbit/s 919 ms with the kernel's buffer (and no bulk
#: priority yet), with bulk priority 113-146 ms at 128 KiB and 64-125 ms at 64 KiB; at
#: 2 Mbit/s 1 140 ms at 128 KiB, 764 ms at 64 KiB (the rest is the link's own queues). 64 KiB
#: is about a 100 Mbit/s WiFi link's bandwidth-delay product at a 5 ms round trip.
CLIENT_LINK_DEFAULTS: Mapping[str, object] = {
    "transport/unicast/open_timeout": 1500,
    "connect/retry": {"period_init_ms": 250, "period_max_ms": 500, "period_increase_factor": 2},
    "transport/link/tx/lease": 10000,
    "transport/link/tx/keep_alive": 4,
    "transport/link/tcp/so_sndbuf": 32768,
}


#: ``open_timeout`` of a robot whose every endpoint is ``udp/``: Zenoh resends nothing of a UDP
#: handshake, so an attempt whose first datagram a dead zone ate waits out the whole timeout;
#: and in the lab a router sometimes took a robot's first datagram after a dead zone and never
#: answered it, so the attempt after it too. With 1.5 s the worst phase came back 1.76 s after
#: the link was usable, with 1 s 2.0-2.2 s (tests/integration/test_reconnect.py); a UDP
#: handshake is two round trips, well within 0.5 s on a WiFi LAN
UDP_OPEN_TIMEOUT_MS = 500


def client_link_defaults(endpoints: Sequence[str]) -> dict[str, object]:
    """``CLIENT_LINK_DEFAULTS`` for a robot connecting to ``endpoints`` (a shorter
    ``open_timeout`` when all are ``udp/``)."""
    defaults = dict(CLIENT_LINK_DEFAULTS)
    if endpoints and all(e.startswith("udp/") for e in endpoints):
        defaults["transport/unicast/open_timeout"] = UDP_OPEN_TIMEOUT_MS
    return defaults
