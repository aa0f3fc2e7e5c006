"""Cache control of seed 001 section 2.3 (Fig. 5): the CEDDP's last line of de-duplication.

Per (robot, topic), a reading identical to the cached value is discarded before planning; a
different one replaces the cache and goes on. After the robots' local caches, what reaches here
identical is mostly the periodic refresh that proves a silent topic alive: the planner does not
need it, the liveness tracking (which sits before cache control) does. Pure logic.
"""

from __future__ import annotations

from dataclasses import dataclass

from arpz.messages import SensorValue, same_value


@dataclass
class CacheControlCounters:
    hits: int = 0
    """readings discarded because they equalled the cached value"""
    misses: int = 0
    """readings passed on to planning (changed, or the first on the topic)"""


class CacheControl:
    def __init__(self, *, enabled: bool = True, tolerance: float = 0.0) -> None:
        self.enabled = enabled
        self.tolerance = tolerance
        self._cache: dict[tuple[str, str], SensorValue] = {}
        self.counters: dict[tuple[str, str], CacheControlCounters] = {}

    def admit(self, robot: str, topic: str, value: SensorValue) -> bool:
        """True if the reading must reach planning, False if it is discarded as a duplicate."""
        slot = (robot, topic)
        counters = self.counters.get(slot)
        if counters is None:
            counters = self.counters[slot] = CacheControlCounters()
        cached = self._cache.get(slot)
        if self.enabled and cached is not None and same_value(value, cached, self.tolerance):
            counters.hits += 1
            return False
        self._cache[slot] = value
        counters.misses += 1
        return True

    def forget(self, robot: str) -> None:
        """Drop a robot's cached values (it left; its next incarnation starts afresh)."""
        for slot in [s for s in self._cache if s[0] == robot]:
            del self._cache[slot]
