"""The perf tool's baselines: raw Zenoh pub/sub (``zenoh``) and zenoh.ext's Advanced
publisher/subscriber (``advanced``). The one module outside ``arpz.transport.zenoh`` that imports
zenoh, as declared in pyproject's import-linter contracts: a baseline must measure Zenoh itself,
not arpz's seam.
"""

from __future__ import annotations

import contextlib
import threading
import time
from typing import Any

import zenoh
import zenoh.ext

from arpz.core.transport import SessionSettings
from arpz.perf.endpoints import STOP, OnPayload
from arpz.transport.zenoh import build_config


def open_session(settings: SessionSettings) -> zenoh.Session:
    return zenoh.open(build_config(settings))


# ------------------------------------------------------------------------------- raw zenoh
class ZenohCounter:
    """A raw subscriber whose callback only counts (no copy of the payload): the cheapest a
    Python subscriber can be, the baseline of benchmarks/ceddp_ingest.py."""

    def __init__(self, session: zenoh.Session, key_expr: str) -> None:
        self._count = 0
        self._lock = threading.Lock()

        def on_sample(_sample: zenoh.Sample) -> None:
            with self._lock:
                self._count += 1

        self._sub = session.declare_subscriber(key_expr, on_sample)

    @property
    def count(self) -> int:
        with self._lock:
            return self._count

    def close(self) -> None:
        self._sub.undeclare()  # type: ignore[no-untyped-call]


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
