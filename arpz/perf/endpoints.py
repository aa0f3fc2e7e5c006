"""The three transports the perf tool compares, behind one small interface: ``arpz`` (the
reliable channel, here) and the two Zenoh baselines (``arpz.perf.zenoh_baselines``)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

from arpz.channel import (
    HistoryFullError,
    QosProfile,
    Reader,
    ReaderEventCallbacks,
    Writer,
)
from arpz.core.link_sizes import writer_fragment_bytes
from arpz.core.protocol.events import DataInfo, MessageLostStatus
from arpz.transport.zenoh import ZenohTransport

TRANSPORTS = ("arpz", "zenoh", "advanced")

#: set by SIGINT/SIGTERM: every loop of the tool, including a KEEP_ALL write retried while no
#: reader acknowledges, gives up at once
STOP = threading.Event()

#: (payload) -> None, called for every received sample on the receiving thread
OnPayload = Callable[[bytes], None]


class Pub(Protocol):
    def wait_matched(self, timeout_s: float) -> bool: ...
    def put(self, payload: bytes) -> None: ...
    def finish(self, linger_s: float) -> dict[str, Any]: ...
    def close(self) -> None: ...


class Sub(Protocol):
    def lost(self) -> int: ...
    def counters(self) -> dict[str, int]: ...
    def close(self) -> None: ...


# ------------------------------------------------------------------------------------ arpz
class ArpzPub:
    """A plain ``Writer``: a sample larger than one fragment (``link_fragment_bytes``, the
    connect endpoints' per ``arpz.core.link_sizes.link_sizes``) goes as fragments, as every arpz
    writer's does."""

    def __init__(
        self,
        transport: ZenohTransport,
        key: str,
        qos: QosProfile,
        express: bool,
        link_fragment_bytes: int | None = None,
    ) -> None:
        self.transport = transport
        fragment_bytes = writer_fragment_bytes(key, link_fragment_bytes)
        self.writer = Writer(transport, key, qos, express=express, fragment_bytes=fragment_bytes)
        self.blocked = 0

    def wait_matched(self, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and not STOP.is_set():
            if self.writer.matched_count and self.writer.wait_for_acknowledgments(0.05):
                return True
            time.sleep(0.02)
        return False

    def put(self, payload: bytes) -> None:
        while True:
            try:
                self.writer.write(payload)
                return
            except HistoryFullError:
                self.blocked += 1  # counted, then retried: the perf tool never drops a sample
                if STOP.is_set():
                    raise

    def finish(self, linger_s: float) -> dict[str, Any]:
        acked = self.writer.wait_for_acknowledgments(linger_s)
        stats = self.writer.stats()
        return {"acknowledged": acked, "blocked_timeouts": self.blocked, **stats_dict(stats)}

    def close(self) -> None:
        self.writer.close()
        self.transport.close()


class ArpzSub:
    def __init__(
        self,
        transport: ZenohTransport,
        key: str,
        qos: QosProfile,
        on_payload: OnPayload,
        inline: bool = False,
    ) -> None:
        self.transport = transport

        def on_data(payload: bytes, info: DataInfo) -> None:
            on_payload(payload)

        def on_lost(status: MessageLostStatus) -> None:
            pass  # the total is read from stats(); the event proves the path works

        events = ReaderEventCallbacks(message_lost=on_lost)
        self.reader = Reader(transport, key, qos, on_data, events=events, inline_delivery=inline)

    def lost(self) -> int:
        return self.reader.stats().lost

    def counters(self) -> dict[str, int]:
        return stats_dict(self.reader.stats())

    def close(self) -> None:
        self.reader.close()
        self.transport.close()


def stats_dict(stats: Any) -> dict[str, Any]:
    return {f: getattr(stats, f) for f in stats.__struct_fields__}
