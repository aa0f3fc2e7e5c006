"""An in-process ``Transport`` for unit tests: same contract as Zenoh, no sockets, synchronous.

Several ``MemoryTransport`` objects attached to one ``MemoryBus`` see each other's puts and
liveliness tokens, as clients of one router would. Delivery is synchronous (the callback runs
inside ``put``), which makes unit tests deterministic; the real router is covered by the
integration tests.
"""

from __future__ import annotations

import queue
import re
import threading
import time
from collections.abc import Callable

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
    TransportError,
)


def _chunk_matches(pattern: str, chunk: str) -> bool:
    if pattern == "*" or pattern == chunk:
        return True
    if "$*" not in pattern:
        return False
    regex = ".*".join(re.escape(part) for part in pattern.split("$*"))
    return re.fullmatch(regex, chunk) is not None


def key_matches(key_expr: str, key: str) -> bool:
    """Zenoh key-expression matching for ``*`` (one chunk), ``**`` (zero or more chunks) and
    ``$*`` (any part of one chunk)."""
    pattern, chunks = key_expr.split("/"), key.split("/")

    def match(i: int, j: int) -> bool:
        if i == len(pattern):
            return j == len(chunks)
        if pattern[i] == "**":
            return any(match(i + 1, k) for k in range(j, len(chunks) + 1))
        if j == len(chunks):
            return False
        return _chunk_matches(pattern[i], chunks[j]) and match(i + 1, j + 1)

    return match(0, 0)


class MemoryBus:
    def __init__(self) -> None:
        self.lock = threading.RLock()
        self.subscribers: list[tuple[str, DataCallback]] = []
        self.watchers: list[tuple[str, LivelinessCallback]] = []
        self.tokens: dict[int, str] = {}
        self.servers: list[tuple[str, QueryHandler]] = []
        self.deferred: list[tuple[str, DeferredQueryHandler]] = []
        self._next_id = 0

    def new_id(self) -> int:
        with self.lock:
            self._next_id += 1
            return self._next_id


class _Handle:
    def __init__(self, on_undeclare: Callable[[], None]) -> None:
        self._on_undeclare: Callable[[], None] | None = on_undeclare

    def undeclare(self) -> None:
        if self._on_undeclare is not None:
            callback, self._on_undeclare = self._on_undeclare, None
            callback()


class _Publisher:
    def __init__(self, transport: MemoryTransport, key: str) -> None:
        self._transport, self._key = transport, key

    def put(self, payload: bytes, *, attachment: bytes | None = None) -> None:
        self._transport.put(self._key, payload, attachment=attachment)

    @property
    def matching(self) -> bool:
        bus = self._transport.bus
        with bus.lock:
            return any(key_matches(expr, self._key) for expr, _ in bus.subscribers)

    def undeclare(self) -> None:
        pass


class _PullSubscriber:
    def __init__(self, capacity: int) -> None:
        self.queue: queue.Queue[tuple[int, Received]] = queue.Queue(maxsize=capacity)
        self.handle: _Handle | None = None
        self.closed = False
        #: when the message last taken was pushed (time.monotonic_ns; 0: none yet)
        self._taken_pushed_ns = 0

    def push(self, key: str, payload: bytes, attachment: bytes | None) -> None:
        # blocks when full: backpressure
        self.queue.put((time.monotonic_ns(), (key, payload, attachment)))

    def try_recv(self) -> Received | None:
        try:
            self._taken_pushed_ns, item = self.queue.get_nowait()
        except queue.Empty:
            return None
        return item

    def recv(self) -> Received:
        while True:
            try:
                self._taken_pushed_ns, item = self.queue.get(timeout=0.02)
                return item
            except queue.Empty:
                if self.closed:  # as Zenoh's FIFO: raise once undeclared and drained
                    raise TransportError("pull subscriber undeclared") from None

    def waited_ns(self) -> int | None:
        if not self._taken_pushed_ns:
            return None
        return time.monotonic_ns() - self._taken_pushed_ns

    def undeclare(self) -> None:
        self.closed = True
        if self.handle is not None:
            self.handle.undeclare()


class MemoryTransport:
    def __init__(self, bus: MemoryBus) -> None:
        self.bus = bus
        self._handles: list[_Handle] = []
        self.closed = False
        #: this transport's liveliness watchers, for ``reopen``: (key expression, the caller's
        #: callback, the bus's entry)
        self._watchers: list[tuple[str, LivelinessCallback, tuple[str, LivelinessCallback]]] = []
        self._reopens = 0
        self._delivered = 0

    @property
    def delivered(self) -> int:
        """Samples, liveliness changes and replies handed to this transport's callbacks."""
        return self._delivered

    @property
    def reopens(self) -> int:
        return self._reopens

    def reopen(self) -> None:
        """As ``ZenohTransport.reopen`` does for its callers: every watcher is told again that
        the tokens alive are there (the new session's history); on an in-process bus nothing
        vanishes meanwhile, and nothing else changes."""
        if self.closed:
            raise TransportError("reopen on a closed MemoryTransport")
        with self.bus.lock:
            watchers = [(e, cb) for e, cb, entry in self._watchers if entry in self.bus.watchers]
            tokens = list(self.bus.tokens.values())
        for expr, callback in watchers:
            for key in sorted({key for key in tokens if key_matches(expr, key)}):
                self._delivered += 1  # the new session's history
                callback(key, True)
        self._reopens += 1

    def publisher(
        self, key: str, *, express: bool = False, block: bool = True, bulk: bool = False
    ) -> Publisher:
        return _Publisher(self, key)

    def put(
        self, key: str, payload: bytes, *, attachment: bytes | None = None, bulk: bool = False
    ) -> None:
        if self.closed:
            raise TransportError("put on a closed MemoryTransport")
        with self.bus.lock:
            targets = [cb for expr, cb in self.bus.subscribers if key_matches(expr, key)]
        for callback in targets:
            callback(key, payload, attachment)

    def subscribe(self, key_expr: str, callback: DataCallback) -> Handle:
        expr, keep = bundle.subscription(key_expr)

        def deliver(key: str, payload: bytes, attachment: bytes | None) -> None:
            self._delivered += 1
            for item in bundle.expand(key, payload, attachment, keep):
                callback(*item)

        entry = (expr, deliver)
        with self.bus.lock:
            self.bus.subscribers.append(entry)

        def remove() -> None:
            with self.bus.lock:
                if entry in self.bus.subscribers:
                    self.bus.subscribers.remove(entry)

        return self._track(_Handle(remove))

    def subscribe_pull(self, key_expr: str, capacity: int) -> PullSubscriber:
        pull = _PullSubscriber(capacity)
        handle = self.subscribe(key_expr, pull.push)
        assert isinstance(handle, _Handle)
        pull.handle = handle
        return pull

    def declare_token(self, key: str) -> Handle:
        token_id = self.bus.new_id()
        with self.bus.lock:
            self.bus.tokens[token_id] = key
            watchers = [cb for expr, cb in self.bus.watchers if key_matches(expr, key)]
        for callback in watchers:
            callback(key, True)

        def remove() -> None:
            with self.bus.lock:
                self.bus.tokens.pop(token_id, None)
                gone = [cb for expr, cb in self.bus.watchers if key_matches(expr, key)]
            for callback in gone:
                callback(key, False)

        return self._track(_Handle(remove))

    def watch_liveliness(self, key_expr: str, callback: LivelinessCallback) -> Handle:
        def counted(key: str, alive: bool) -> None:
            self._delivered += 1
            callback(key, alive)

        entry = (key_expr, counted)
        self._watchers.append((key_expr, callback, entry))
        with self.bus.lock:
            self.bus.watchers.append(entry)
            present = [k for k in self.bus.tokens.values() if key_matches(key_expr, k)]
        for key in present:
            callback(key, True)

        def remove() -> None:
            with self.bus.lock:
                if entry in self.bus.watchers:
                    self.bus.watchers.remove(entry)

        return self._track(_Handle(remove))

    def serve(self, key: str, handler: QueryHandler) -> Handle:
        entry = (key, handler)
        with self.bus.lock:
            self.bus.servers.append(entry)

        def remove() -> None:
            with self.bus.lock:
                if entry in self.bus.servers:
                    self.bus.servers.remove(entry)

        return self._track(_Handle(remove))

    def request(
        self, key: str, payload: bytes, on_reply: ReplyCallback, *, timeout_s: float
    ) -> None:
        """Answered at once, inside the call (no timeout can pass on an in-process bus)."""
        if self.closed:
            raise TransportError("request on a closed MemoryTransport")
        with self.bus.lock:
            handlers = [h for expr, h in self.bus.servers if key_matches(expr, key)]
        for handler in handlers:
            answer = handler(payload)
            if answer is not None:
                self._delivered += 1
                on_reply(answer)

    def serve_deferred(self, key_expr: str, handler: DeferredQueryHandler) -> Handle:
        entry = (key_expr, handler)
        with self.bus.lock:
            self.bus.deferred.append(entry)

        def remove() -> None:
            with self.bus.lock:
                if entry in self.bus.deferred:
                    self.bus.deferred.remove(entry)

        return self._track(_Handle(remove))

    def query(
        self,
        key: str,
        payload: bytes,
        on_reply: ReplyCallback,
        on_done: DoneCallback,
        *,
        timeout_s: float,
    ) -> None:
        """Each handler runs inside the call, as Zenoh's queryable thread would run it; its
        responder replies from any thread until it finishes or ``timeout_s`` passes (a timer
        thread), and ``on_done`` follows the last finish, the timeout, or at once when no
        queryable matches ``key``."""
        if self.closed:
            raise TransportError("query on a closed MemoryTransport")
        with self.bus.lock:
            handlers = [h for expr, h in self.bus.deferred if key_matches(expr, key)]
        if not handlers:
            on_done()
            return
        state = _Query(len(handlers), on_done, timeout_s)

        def deliver(answer: bytes) -> bool:
            if self.closed:
                return False
            self._delivered += 1
            on_reply(answer)
            return True

        for handler in handlers:
            handler(key, payload, _MemoryResponder(state, deliver))

    def _track(self, handle: _Handle) -> _Handle:
        self._handles.append(handle)
        return handle

    def close(self) -> None:
        if self.closed:
            return
        for handle in reversed(self._handles):
            handle.undeclare()
        self._handles.clear()
        self.closed = True


class _Query:
    """One request of ``MemoryTransport.query``: over when every responder finished or its
    timeout passed, whichever comes first."""

    def __init__(self, repliers: int, on_done: DoneCallback, timeout_s: float) -> None:
        self.lock = threading.Lock()
        self.pending = repliers
        self.over = False
        self._on_done = on_done
        self._timer = threading.Timer(timeout_s, self.end)
        self._timer.daemon = True
        self._timer.start()

    def finished_one(self) -> None:
        with self.lock:
            self.pending -= 1
            last = self.pending == 0
        if last:
            self.end()

    def end(self) -> None:
        with self.lock:
            if self.over:
                return
            self.over = True
        self._timer.cancel()
        self._on_done()


class _MemoryResponder:
    #: the bus carries no attachments (``Responder.attachment``)
    attachment: bytes | None = None

    def __init__(self, state: _Query, deliver: Callable[[bytes], bool]) -> None:
        self._state = state
        self._deliver = deliver
        self._finished = False

    def reply(self, payload: bytes, *, attachment: bytes | None = None) -> bool:
        with self._state.lock:
            if self._finished or self._state.over:
                return False
        return self._deliver(payload)

    def finish(self) -> None:
        if self._finished:
            return
        self._finished = True
        self._state.finished_one()
