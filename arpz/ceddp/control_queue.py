"""The CEDDP's queue of reports and presence events: bounded, and the latest per key.

Reports (stats, announcements, telemetry, QoS acks), presence and mode tokens, QoS requests and
incompatibility notices are all state: only the newest of one key matters (stats are cumulative,
an announcement replaces the previous one, telemetry is a pose). So a second item for a key that
is still waiting replaces the first in place (counted ``coalesced``) instead of queueing behind
it: a robot flooding its own report keys costs one slot per key, and every other robot's
reports wait at most one pass of the queue behind it. Distinct keys are bounded by ``limit``;
beyond, items are refused and counted ``dropped`` (by kind), never silently.
"""

from __future__ import annotations

import threading
from collections import Counter, OrderedDict

Item = tuple[int, str, bytes]


class ControlQueue:
    def __init__(self, limit: int) -> None:
        if limit < 1:
            raise ValueError(f"limit must be >= 1, got {limit}")
        self.limit = limit
        self._items: OrderedDict[tuple[int, str], bytes] = OrderedDict()
        self._ready = threading.Condition()
        self._closed = False
        self.coalesced = 0
        self.dropped: Counter[int] = Counter()
        self.peak = 0

    def put(self, kind: int, key: str, payload: bytes) -> bool:
        """Queue (or replace the waiting item of) ``(kind, key)``; False when refused."""
        slot = (kind, key)
        with self._ready:
            if slot in self._items:
                self._items[slot] = payload  # keeps its place: first come, first served
                self.coalesced += 1
                return True
            if len(self._items) >= self.limit:
                self.dropped[kind] += 1
                return False
            self._items[slot] = payload
            self.peak = max(self.peak, len(self._items))
            self._ready.notify()
            return True

    def get(self) -> Item | None:
        """The oldest waiting item, blocking; None once closed and empty."""
        with self._ready:
            while not self._items:
                if self._closed:
                    return None
                self._ready.wait()
            (kind, key), payload = self._items.popitem(last=False)
            return kind, key, payload

    def close(self) -> None:
        """Let ``get`` return None once what is queued has been taken."""
        with self._ready:
            self._closed = True
            self._ready.notify_all()

    def __len__(self) -> int:
        with self._ready:
            return len(self._items)
