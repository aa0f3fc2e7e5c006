"""A user-space UDP proxy that impairs the link between a Zenoh client and its router.

The client connects to ``udp/LISTEN``; for each client address the proxy opens its own upstream
socket to ``udp/FORWARD``, so the router sees one peer per client and its replies come back on
the socket that knows where to return them. One thread, one selector, one heap of timed sends:
no per-datagram threads, and the impairment decisions come from ``model.Direction``.
"""

from __future__ import annotations

import contextlib
import heapq
import itertools
import os
import random
import selectors
import socket
import threading
import time
from dataclasses import dataclass

from arpz.netem.model import Counters, Direction, Impairments

_MAX_DATAGRAM = 65535
#: receive buffer asked for each socket (the kernel caps it at net.core.rmem_max): a sender that
#: bursts hundreds of datagrams (Zenoh fragmenting a large sample) must not overflow the default
#: 208 KiB before the proxy's thread reads them, or the emulator adds loss of its own
_RCVBUF_BYTES = 8 * 2**20


def _big_buffer(sock: socket.socket) -> socket.socket:
    with contextlib.suppress(OSError):
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, _RCVBUF_BYTES)
    return sock


def kernel_drops(socks: list[socket.socket] | None = None, *, port: int | None = None) -> int:
    """Datagrams the kernel dropped on UDP sockets (full receive buffer), from the ``drops``
    column of /proc/net/udp: of ``socks`` (matched by inode), or of whatever socket is bound to
    local ``port`` (e.g. a router's, to see what a burst cost it); 0 where the file is missing."""
    inodes = {os.fstat(s.fileno()).st_ino for s in socks or [] if s.fileno() >= 0}
    total = 0
    for table in ("/proc/net/udp", "/proc/net/udp6"):
        try:
            with open(table) as fh:
                lines = fh.read().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            if len(fields) <= 12:
                continue
            local_port = int(fields[1].rpartition(":")[2], 16)
            if int(fields[9]) in inodes or local_port == port:
                total += int(fields[12])
    return total


def parse_udp_endpoint(endpoint: str) -> tuple[str, int]:
    """``udp/HOST:PORT`` (the Zenoh spelling) or ``HOST:PORT`` -> (host, port)."""
    text = endpoint.removeprefix("udp/")
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise ValueError(f"endpoint {endpoint!r} must look like udp/HOST:PORT")
    return host.strip("[]"), int(port)


@dataclass
class ProxyReport:
    up: Counters
    down: Counters
    clients: int
    elapsed_s: float

    def as_dict(self) -> dict[str, object]:
        def one(c: Counters) -> dict[str, int]:
            return {**vars(c), "dropped": c.dropped}

        return {
            "elapsed_s": round(self.elapsed_s, 3),
            "clients": self.clients,
            "up": one(self.up),
            "down": one(self.down),
        }


class NetemProxy:
    """Forward datagrams between ``listen`` and ``forward`` with impairments in both directions
    (``down`` may differ from ``up``: an asymmetric link)."""

    def __init__(
        self,
        listen: str,
        forward: str,
        up: Impairments,
        down: Impairments | None = None,
        *,
        seed: int | None = None,
    ) -> None:
        self._listen_addr = parse_udp_endpoint(listen)
        self._forward_addr = parse_udp_endpoint(forward)
        rng = random.Random(seed)
        self.up = Direction(up, random.Random(rng.random()))
        self.down = Direction(down if down is not None else up, random.Random(rng.random()))
        self._sel = selectors.DefaultSelector()
        self._listen = _big_buffer(socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
        self._listen.bind(self._listen_addr)
        self._listen.setblocking(False)
        self._sel.register(self._listen, selectors.EVENT_READ, None)
        self._upstream: dict[tuple[str, int], socket.socket] = {}
        self._heap: list[tuple[float, int, socket.socket, bytes, tuple[str, int], Counters]] = []
        self._order = itertools.count()
        self._stop = threading.Event()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._t0 = time.monotonic()
        self._thread: threading.Thread | None = None
        self._closed = False

    @property
    def listen_port(self) -> int:
        return int(self._listen.getsockname()[1])

    @property
    def elapsed_s(self) -> float:
        """Seconds since the proxy was made: the clock of ``clean_s`` and ``Outage.start_s``."""
        return time.monotonic() - self._t0

    def set_impairments(self, up: Impairments, down: Impairments | None = None) -> None:
        """Change the link while it runs (read per datagram: takes effect at once); e.g. an
        outage from now: ``Impairments(clean_s=proxy.elapsed_s, outages=(Outage(start_s=0,
        duration_s=5),))``."""
        self.up.imp = up
        self.down.imp = down if down is not None else up

    def start(self) -> NetemProxy:
        self._thread = threading.Thread(target=self.run, name="arpz-netem", daemon=True)
        self._thread.start()
        return self

    def request_stop(self) -> None:
        """Safe from a signal handler: the loop notices within its select timeout."""
        self._stop.set()

    def stop(self) -> ProxyReport:
        self._stop.set()
        # The loop may already have ended (its --duration elapsed) and closed the socket.
        with contextlib.suppress(OSError):
            self._wake_w.send(b"x")
        if self._thread is not None:
            self._thread.join(timeout=5)
        return self.report()

    def report(self) -> ProxyReport:
        if not self._closed:
            self._count_overflow()
        return ProxyReport(
            self.up.counters, self.down.counters, len(self._upstream), time.monotonic() - self._t0
        )

    def run(self, duration_s: float | None = None) -> ProxyReport:
        end = self._t0 + duration_s if duration_s else None
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                if end is not None and now >= end:
                    break
                self._flush(now)
                timeout = 0.2
                if self._heap:
                    timeout = min(timeout, max(0.0, self._heap[0][0] - now))
                if end is not None:
                    timeout = min(timeout, max(0.0, end - now))
                for key, _ in self._sel.select(timeout):
                    if key.data == "wake":
                        self._wake_r.recv(64)
                    else:
                        self._receive(key.fileobj, key.data)  # type: ignore[arg-type]
        finally:
            self._count_overflow()
            self._close()
        return self.report()

    def _receive(self, sock: socket.socket, client: tuple[str, int] | None) -> None:
        """Drain the socket: datagrams from a client (``client`` None) or from the router."""
        for _ in range(256):
            try:
                data, addr = sock.recvfrom(_MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:  # ICMP port unreachable from a vanished peer
                return
            now = time.monotonic()
            if client is None:
                out = self._upstream.get(addr)
                if out is None:
                    out = _big_buffer(socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
                    out.bind((self._listen_addr[0], 0))
                    out.setblocking(False)
                    self._upstream[addr] = out
                    self._sel.register(out, selectors.EVENT_READ, addr)
                self._schedule(self.up, out, data, self._forward_addr, now)
            else:
                self._schedule(self.down, self._listen, data, client, now)

    def _schedule(
        self,
        direction: Direction,
        sock: socket.socket,
        data: bytes,
        dest: tuple[str, int],
        now: float,
    ) -> None:
        for when in direction.fate(len(data), now - self._t0, now):
            if when <= now and not self._heap:
                self._send(sock, data, dest, direction.counters)
            else:
                item = (when, next(self._order), sock, data, dest, direction.counters)
                heapq.heappush(self._heap, item)

    def _flush(self, now: float) -> None:
        while self._heap and self._heap[0][0] <= now:
            _, _, sock, data, dest, counters = heapq.heappop(self._heap)
            self._send(sock, data, dest, counters)

    @staticmethod
    def _send(sock: socket.socket, data: bytes, dest: tuple[str, int], counters: Counters) -> None:
        try:
            sock.sendto(data, dest)
        except OSError:  # a full socket buffer or a vanished peer: lost, as on a real link
            counters.send_errors += 1
            counters.forwarded -= 1
            counters.bytes_out -= len(data)

    def _count_overflow(self) -> None:
        """Kernel drops on the listening socket were datagrams from the clients (up); on the
        upstream sockets, from the router (down)."""
        with contextlib.suppress(OSError, ValueError, RuntimeError):  # RuntimeError: a new
            # client's socket added while another thread asks for the report
            self.up.counters.rx_overflow = kernel_drops([self._listen])
            self.down.counters.rx_overflow = kernel_drops(list(self._upstream.values()))

    def _close(self) -> None:
        self._closed = True
        for sock in [self._listen, *self._upstream.values(), self._wake_r, self._wake_w]:
            with contextlib.suppress(KeyError, ValueError):
                self._sel.unregister(sock)
            sock.close()
