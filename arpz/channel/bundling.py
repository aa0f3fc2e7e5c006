"""``Bundler``: a ``Transport`` whose sensor publishers share one Zenoh message per tick.

The robot's scheduler runs every job due at one instant inside ``collect()``; what its sensor
writers put there is held and leaves, when the tick ends, as one bundle per sibling group
(``arpz.core.protocol.bundle``) instead of one Zenoh message per topic. Nothing waits for a timer:
the bundle goes out as soon as the tick's last job returns, so a tick's first sample gains only
the time its siblings take to be read and written (microseconds on a robot).

Outside ``collect()`` (a writer's worker sending heartbeats or resends, any other thread) every
put goes straight to Zenoh as before. A reliable writer asks ``will_hold`` before its put and
its heartbeats stop short of a held message until ``on_released``: a heartbeat that overtook the
bundle announced seqs the reader could only NACK (issue 17). A bundle the link
refuses (the session closed) loses only transmissions: the samples stay in the writers' histories
and are recovered by NACK, as a lost datagram would be; the refusal is counted and logged.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Callable, Iterator

from arpz.core.protocol import bundle
from arpz.core.throttled_log import ThrottledLog
from arpz.core.transport import (
    DataCallback,
    Handle,
    LivelinessCallback,
    Publisher,
    PullSubscriber,
    QueryHandler,
    ReplyCallback,
    Transport,
    TransportError,
)

log = logging.getLogger("arpz.channel.bundling")
#: bytes a bundle adds per entry besides its name, attachment and payload (the length table)
_ENTRY_OVERHEAD = 7


class BundleStats:
    """Counters of one ``Bundler`` (read without a lock: plain ints, one writing thread)."""

    def __init__(self) -> None:
        #: bundles sent, and the messages they carried
        self.bundles = 0
        self.bundled = 0
        #: messages of a tick that went alone (the only one of its tick, or too large)
        self.single = 0
        #: bundles the link refused, and the messages in them (the channel recovers those)
        self.put_failures = 0
        self.failed_messages = 0


class _BundledPublisher:
    def __init__(self, bundler: Bundler, key: str, inner: Publisher) -> None:
        self._bundler = bundler
        self.key = key
        self.name = key.rpartition("/")[2]
        self.parent_key = bundle.bundle_key(key) or ""
        self.inner = inner
        #: called (on the tick's thread) once a bundle holding a message of this publisher
        #: left or was refused: a reliable writer's heartbeats announce its seqs again
        self.on_released: Callable[[], None] | None = None

    def _fits(self, payload: bytes, attachment: bytes | None) -> bool:
        return len(payload) + len(attachment or b"") <= self._bundler.max_bytes and (
            attachment is None or len(attachment) <= bundle.MAX_ATTACHMENT
        )

    def will_hold(self, payload: bytes, attachment: bytes | None) -> bool:
        """Whether ``put`` of this message on the calling thread holds it until the tick ends."""
        return self._bundler.held() is not None and self._fits(payload, attachment)

    def put(self, payload: bytes, *, attachment: bytes | None = None) -> None:
        held = self._bundler.held()
        if held is None or not self._fits(payload, attachment):
            self.inner.put(payload, attachment=attachment)
            return
        held.append((self, payload, attachment))

    def release_held(self) -> None:
        """Send what this thread holds now (a writer about to wait for acknowledgements: some
        of what it waits for may be in the open bundle)."""
        self._bundler.send_held()

    @property
    def matching(self) -> bool:
        return self.inner.matching

    def undeclare(self) -> None:
        self.inner.undeclare()


_Held = tuple[_BundledPublisher, bytes, bytes | None]


class Bundler:
    """Wraps ``transport``; publishers of ``.../sensor/{topic}`` keys it declares bundle what one
    thread puts inside ``collect()``. ``max_bytes``: a bundle's size at most (the link's safe
    message size: one radio frame on UDP, so that Zenoh never fragments a bundle)."""

    def __init__(self, transport: Transport, *, max_bytes: int) -> None:
        if max_bytes < 256:
            raise ValueError(f"max_bytes must be >= 256, got {max_bytes}")
        self.transport = transport
        self.max_bytes = max_bytes
        self.stats = BundleStats()
        self._local = threading.local()
        self._bundle_publishers: dict[str, Publisher] = {}
        self._lock = threading.Lock()
        self._bad = ThrottledLog(log)

    def held(self) -> list[_Held] | None:
        """The calling thread's open bundle, None outside ``collect()``."""
        held: list[_Held] | None = getattr(self._local, "held", None)
        return held

    @contextlib.contextmanager
    def collect(self) -> Iterator[None]:
        """Hold what this thread's bundled publishers put, and send it as bundles at the end
        (nested calls join the outer one)."""
        if self.held() is not None:
            yield
            return
        held: list[_Held] = []
        self._local.held = held
        try:
            yield
        finally:
            self._local.held = None
            if held:
                self._send(held)

    def send_held(self) -> None:
        """Send what the calling thread's open bundle holds so far; it stays open."""
        held = self.held()
        if held:
            taken = list(held)
            held.clear()
            self._send(taken)

    def _send(self, held: list[_Held]) -> None:
        """Send ``held``, then tell its publishers their messages left."""
        try:
            self._send_bundles(held)
        finally:
            released = {id(item[0]): item[0] for item in held}
            for publisher in released.values():
                if publisher.on_released is not None:
                    publisher.on_released()

    def _send_bundles(self, held: list[_Held]) -> None:
        """Cut ``held`` (in put order) into bundles of one sibling group within ``max_bytes``."""
        group: list[_Held] = []
        size = 0
        for item in held:
            publisher, payload, attachment = item
            cost = len(publisher.name) + len(payload) + len(attachment or b"") + _ENTRY_OVERHEAD
            if group and (
                publisher.parent_key != group[0][0].parent_key
                or size + cost > self.max_bytes
                or len(group) >= bundle.MAX_ENTRIES
            ):
                self._send_group(group)
                group, size = [], 0
            group.append(item)
            size += cost
        self._send_group(group)

    def _send_group(self, group: list[_Held]) -> None:
        if len(group) == 1:
            publisher, payload, attachment = group[0]
            self.stats.single += 1
            self._put(publisher.inner, payload, attachment, 1)
            return
        payload, attachment = bundle.encode(
            [(publisher.name, data, att) for publisher, data, att in group]
        )
        self.stats.bundles += 1
        self.stats.bundled += len(group)
        self._put(self._publisher_for(group[0][0].parent_key), payload, attachment, len(group))

    def _put(
        self, publisher: Publisher, payload: bytes, attachment: bytes | None, messages: int
    ) -> None:
        try:
            publisher.put(payload, attachment=attachment)
        except TransportError as exc:
            self.stats.put_failures += 1
            self.stats.failed_messages += messages
            self._bad.warning(
                "bundle put failed", "bundle put failed (%d messages): %s", messages, exc
            )

    def _publisher_for(self, key: str) -> Publisher:
        with self._lock:
            publisher = self._bundle_publishers.get(key)
            if publisher is None:
                # DROP, as the robots' sensor writers: a stalled server never stalls the tick
                publisher = self.transport.publisher(key, block=False)
                self._bundle_publishers[key] = publisher
            return publisher

    # -- Transport ------------------------------------------------------------------------------

    def publisher(
        self, key: str, *, express: bool = False, block: bool = True, bulk: bool = False
    ) -> Publisher:
        inner = self.transport.publisher(key, express=express, block=block, bulk=bulk)
        if express or bulk or bundle.bundle_key(key) is None:
            return inner
        return _BundledPublisher(self, key, inner)

    def put(
        self, key: str, payload: bytes, *, attachment: bytes | None = None, bulk: bool = False
    ) -> None:
        if bulk:
            self.transport.put(key, payload, attachment=attachment, bulk=True)
        else:
            self.transport.put(key, payload, attachment=attachment)

    def subscribe(self, key_expr: str, callback: DataCallback) -> Handle:
        return self.transport.subscribe(key_expr, callback)

    def subscribe_pull(self, key_expr: str, capacity: int) -> PullSubscriber:
        return self.transport.subscribe_pull(key_expr, capacity)

    def declare_token(self, key: str) -> Handle:
        return self.transport.declare_token(key)

    def watch_liveliness(self, key_expr: str, callback: LivelinessCallback) -> Handle:
        return self.transport.watch_liveliness(key_expr, callback)

    def serve(self, key: str, handler: QueryHandler) -> Handle:
        return self.transport.serve(key, handler)

    def request(
        self, key: str, payload: bytes, on_reply: ReplyCallback, *, timeout_s: float
    ) -> None:
        self.transport.request(key, payload, on_reply, timeout_s=timeout_s)

    def close(self) -> None:
        """The wrapped transport belongs to its opener, who closes it."""
