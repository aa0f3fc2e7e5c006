"""Helpers shared by the tests: free ports, polling waits, a real in-process Zenoh router."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from arpz.core.protocol import wire
from arpz.core.transport import SessionSettings, TransportError
from arpz.tools.launch import PORT_TAKEN_LOG, free_port  # free_port: the tests import it from here
from arpz.transport.zenoh import ZenohTransport


def free_udp_port() -> int:
    return free_port(socket.SOCK_DGRAM)


def wait_until(
    predicate: Callable[[], bool],
    *,
    timeout_s: float = 10.0,
    what: str = "condition",
    interval_s: float = 0.02,
    raise_on_timeout: bool = True,
) -> bool:
    """Poll ``predicate`` until true; after ``timeout_s`` fail naming ``what``, or, with
    ``raise_on_timeout=False``, return False (a caller that retries, such as a request that
    may have gone before anyone answered)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(interval_s)
    if predicate():
        return True
    if raise_on_timeout:
        raise AssertionError(f"timed out after {timeout_s:.1f} s waiting for {what}")
    return False


class HeldHeartbeats:
    """A transport callback for a writer's heartbeats that notes, for each, the seq a bundle
    held when it arrived (``holding``, set by the test around its hold; 0 outside one). It
    runs on the transport's thread, where a failed assert would be logged and lost: what does
    not decode is counted in ``undecodable`` for the test to check."""

    def __init__(self) -> None:
        self.holding = 0
        self.seen: list[tuple[int, int]] = []  # (seq held then, last seq announced)
        self.undecodable = 0

    def __call__(self, _key: str, payload: bytes, _attachment: bytes | None) -> None:
        heartbeat = wire.decode_heartbeat(payload)
        if heartbeat is None:
            self.undecodable += 1
            return
        self.seen.append((self.holding, heartbeat.last))

    def during_holds(self) -> list[tuple[int, int]]:
        return [(held, last) for held, last in self.seen if held]


class SlowFirstDelivery:
    """An ``on_data`` that is busy on the sample ``first`` until ``queue_behind`` has seen the
    samples behind it arrive, then ``busy_s`` more (the delivery thread cannot take what
    arrives meanwhile: it waits in the transport's queue). Busy for a fixed time from the
    first sample instead, a loaded machine could bring the others after the busy spell, with
    nothing queued (seen in CI)."""

    def __init__(self, first: bytes = b"first", busy_s: float = 0.3) -> None:
        self.first = first
        self.busy_s = busy_s
        self.started = threading.Event()
        self.release = threading.Event()
        self.done: list[bytes] = []

    def __call__(self, payload: bytes, _info: object) -> None:
        if payload == self.first:
            self.started.set()
            self.release.wait(10.0)  # deliberately: the delivery thread is busy
            time.sleep(self.busy_s)
        self.done.append(payload)

    def queue_behind(
        self,
        write: Callable[[bytes], object],
        more: int = 5,
        arrived_through: Callable[[], int] | None = None,
    ) -> None:
        """Write ``first``, then ``more`` samples while it is being delivered; wait until
        ``arrived_through`` (the highest seq the reader's session received, ``SeqProbe``) says
        they all arrived, when given; then let the delivery go on and wait for all."""
        write(self.first)
        assert self.started.wait(5.0), "the first sample was never delivered"
        for i in range(more):
            write(str(i).encode())
        if arrived_through is not None:
            wait_until(lambda: arrived_through() >= more + 1, what="the samples behind it arrive")
        self.release.set()
        wait_until(lambda: len(self.done) == more + 1, what=f"all {more + 1} delivered")


class SeqProbe:
    """A transport callback on a reliable topic's data key: the highest seq received (a DATA
    message or a batch). Declared on the reader's session it says what reached the reader's
    queue, which the queue itself does not."""

    def __init__(self) -> None:
        self.highest = 0

    def __call__(self, _key: str, payload: bytes, attachment: bytes | None) -> None:
        header = wire.decode_data(attachment)
        if header is not None:
            self.highest = max(self.highest, header.seq)
            return
        batch = wire.decode_batch(payload, attachment) if attachment is not None else None
        if batch is not None:
            self.highest = max(self.highest, batch.first + len(batch.payloads) - 1)


#: fresh ports ``router`` tries when the one it chose was taken meanwhile
ROUTER_PORT_TRIES = 3


@contextmanager
def router(
    port: int | None = None, config_file: str | None = None
) -> Iterator[tuple[ZenohTransport, str]]:
    """A real Zenoh router (a Python session in router mode) on loopback.

    Yields (transport, endpoint). Without ``port``, one that another process takes between
    ``free_port`` and the bind is replaced by a new one (up to 3 tries), as ``arpz.tools.launch``
    does for the tools (the race failed a CI run in stop 38, there in an experiment's CEDDP)."""
    for attempt in range(1, ROUTER_PORT_TRIES + 1):
        endpoint = f"tcp/127.0.0.1:{port or free_port()}"
        try:
            transport = ZenohTransport.open(
                SessionSettings(mode="router", listen=[endpoint], config_file=config_file)
            )
            break
        except TransportError as exc:
            if port is not None or attempt == ROUTER_PORT_TRIES or PORT_TAKEN_LOG not in str(exc):
                raise
    try:
        yield transport, endpoint
    finally:
        transport.close()


@contextmanager
def client(endpoint: str) -> Iterator[ZenohTransport]:
    transport = ZenohTransport.open(SessionSettings(mode="client", connect=[endpoint]), timeout_s=5)
    try:
        yield transport
    finally:
        transport.close()


def gil_waits_ms(pace: Callable[[], None] | None, seconds: float) -> list[float]:
    """While a pure-Python loop runs for ``seconds`` on another thread (calling ``pace`` at each
    step, e.g. an ``arpz.ceddp.pacing.Pacer``), how long this thread waits, each time, to get
    the GIL back after giving it up for 1 ms (ms, in order). Stands for the CEDDP's sensor path
    (which gives the GIL up whenever it blocks for data) against its background loops."""
    started = threading.Event()

    def busy() -> None:
        started.set()
        end = time.perf_counter() + seconds
        while time.perf_counter() < end:
            sum(range(200))  # pure Python: the GIL is held between the checks
            if pace is not None:
                pace()

    worker = threading.Thread(target=busy, daemon=True)
    worker.start()
    started.wait(5)
    waits: list[float] = []
    while worker.is_alive():
        before = time.perf_counter()
        time.sleep(0.001)  # gives the GIL up; taking it back waits for the loop
        waits.append((time.perf_counter() - before - 0.001) * 1e3)
    worker.join(5)
    return waits
