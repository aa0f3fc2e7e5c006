"""The three transports the perf tool compares, behind one small interface.

``arpz`` is the reliable channel (through ``arpz.transport``); ``zenoh`` (raw pub/sub) and
``advanced`` (zenoh.ext AdvancedPublisher/AdvancedSubscriber) are the baselines, and as such the
only code outside ``arpz.transport`` allowed to import zenoh: they must measure Zenoh itself.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

import zenoh
import zenoh.ext

from arpz.reliability import (
    HistoryFullError,
    QosProfile,
    Reader,
    ReaderEventCallbacks,
    Writer,
)
from arpz.reliability.events import DataInfo, MessageLostStatus
from arpz.transport import SessionSettings, ZenohTransport, build_config

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


def open_session(settings: SessionSettings) -> zenoh.Session:
    return zenoh.open(build_config(settings))


# ------------------------------------------------------------------------------------ arpz
class ArpzPub:
    def __init__(self, transport: ZenohTransport, key: str, qos: QosProfile, express: bool) -> None:
        self.transport = transport
        self.writer = Writer(transport, key, qos, express=express)
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


# ------------------------------------------------------------------------------- raw zenoh
class ZenohPub:
    def __init__(self, session: zenoh.Session, key: str, express: bool) -> None:
        self.session = session
        self.pub: Any = session.declare_publisher(
            key, congestion_control=zenoh.CongestionControl.BLOCK, express=express
        )

    def wait_matched(self, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and not STOP.is_set():
            if self.pub.matching_status.matching:
                return True
            time.sleep(0.02)
        return False

    def put(self, payload: bytes) -> None:
        self.pub.put(payload)

    def finish(self, linger_s: float) -> dict[str, Any]:
        time.sleep(min(linger_s, 0.5))  # nothing to wait for: raw Zenoh acknowledges nothing
        return {}

    def close(self) -> None:
        self.pub.undeclare()
        self.session.close()  # type: ignore[no-untyped-call]


class ZenohSub:
    def __init__(self, session: zenoh.Session, key: str, on_payload: OnPayload) -> None:
        self.session = session

        def on_sample(sample: zenoh.Sample) -> None:
            on_payload(sample.payload.to_bytes())

        self.sub = session.declare_subscriber(key, on_sample)

    def lost(self) -> int:
        return 0  # raw Zenoh never reports a loss

    def counters(self) -> dict[str, int]:
        return {}

    def close(self) -> None:
        self.sub.undeclare()  # type: ignore[no-untyped-call]
        self.session.close()  # type: ignore[no-untyped-call]


# ----------------------------------------------------------------------- zenoh.ext Advanced
class AdvancedPub(ZenohPub):
    def __init__(self, session: zenoh.Session, key: str, express: bool, cache: int) -> None:
        self.session = session
        self.pub = zenoh.ext.declare_advanced_publisher(
            session,
            key,
            congestion_control=zenoh.CongestionControl.BLOCK,
            express=express,
            cache=zenoh.ext.CacheConfig(max_samples=cache),
            sample_miss_detection=zenoh.ext.MissDetectionConfig(
                heartbeat=0.1, sporadic_heartbeat=None
            ),
            publisher_detection=True,
        )
        self._matched_at = time.monotonic()

    def wait_matched(self, timeout_s: float) -> bool:
        time.sleep(min(timeout_s, 1.0))  # no matching status on AdvancedPublisher
        return True


class AdvancedSub:
    def __init__(self, session: zenoh.Session, key: str, on_payload: OnPayload) -> None:
        self.session = session
        self._missed = 0
        self._lock = threading.Lock()

        def on_sample(sample: zenoh.Sample) -> None:
            on_payload(sample.payload.to_bytes())

        self.sub = zenoh.ext.declare_advanced_subscriber(
            session,
            key,
            on_sample,
            history=zenoh.ext.HistoryConfig(detect_late_publishers=True),
            recovery=zenoh.ext.RecoveryConfig(periodic_queries=None, heartbeat=True),
            subscriber_detection=True,
        )

        def on_miss(miss: zenoh.ext.Miss) -> None:
            with self._lock:
                self._missed += int(miss.nb)

        self.listener = self.sub.sample_miss_listener(on_miss)

    def lost(self) -> int:
        with self._lock:
            return self._missed

    def counters(self) -> dict[str, int]:
        return {"missed": self.lost()}

    def close(self) -> None:
        # zenoh raises its own error type if the session is already closing
        with contextlib.suppress(Exception):
            self.listener.undeclare()  # type: ignore[no-untyped-call]
        self.sub.undeclare()  # type: ignore[no-untyped-call]
        self.session.close()  # type: ignore[no-untyped-call]
