"""Helpers shared by the tests: free ports, polling waits, a real in-process Zenoh router."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from arpz.transport import SessionSettings, ZenohTransport


def free_port() -> int:
    """A TCP port that was free a moment ago (bind to 0 and release)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def wait_until(
    predicate: Callable[[], bool],
    *,
    timeout_s: float = 10.0,
    what: str = "condition",
    interval_s: float = 0.02,
) -> None:
    """Poll ``predicate`` until true; after ``timeout_s`` fail naming ``what``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(interval_s)
    if predicate():
        return
    raise AssertionError(f"timed out after {timeout_s:.1f} s waiting for {what}")


@contextmanager
def router(port: int | None = None) -> Iterator[tuple[ZenohTransport, str]]:
    """A real Zenoh router (a Python session in router mode) on loopback.

    Yields (transport, endpoint)."""
    port = port or free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    transport = ZenohTransport.open(SessionSettings(mode="router", listen=[endpoint]))
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
