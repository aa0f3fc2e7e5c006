"""Cache control of seed 001 section 2.3 (Fig. 5): the CEDDP's last line of de-duplication.

Per (robot, topic), a reading identical to the cached value is discarded before planning; a
different one replaces the cache and goes on. After the robots' local caches, what reaches here
identical is mostly the periodic refresh that proves a silent topic alive: the planner does not
need it, the liveness tracking (which sits before cache control) does. Pure logic.
"""

from __future__ import annotations

from dataclasses import dataclass

from arpz.core.messages import SensorValue, same_value
from arpz.core.msgtypes import same_message


@dataclass
class CacheControlCounters:
    hits: int = 0
    """readings discarded because they equalled the cached value"""
    misses: int = 0
    """readings passed on to planning (changed, or the first on the topic)"""


@dataclass
class CacheSlot(CacheControlCounters):
    """The cache of one (robot, topic); the ingest keeps a reference to skip the lookups."""

    enabled: bool = True
    tolerance: float = 0.0
    has_value: bool = False
    value: object = 0.0
    #: a typed topic: its messages are compared whole, header stamp excluded
    typed: bool = False

    def admit(self, value: object) -> bool:
        if (
            self.enabled
            and self.has_value
            and (
                (type(value) is type(self.value) and value == self.value)
                or (self.typed and same_message(value, self.value))
                or (
                    self.tolerance and same_value(value, self.value, self.tolerance)  # type: ignore[arg-type]
                )
            )
        ):
            self.hits += 1
            return False
        self.value = value
        self.has_value = True
        self.misses += 1
        return True


class CacheControl:
    def __init__(self, *, enabled: bool = True, tolerance: float = 0.0) -> None:
        self.enabled = enabled
        self.tolerance = tolerance
        self.counters: dict[tuple[str, str], CacheSlot] = {}

    def slot(self, robot: str, topic: str) -> CacheSlot:
        slot = self.counters.get((robot, topic))
        if slot is None:
            slot = self.counters[(robot, topic)] = CacheSlot(
                enabled=self.enabled, tolerance=self.tolerance
            )
        return slot

    def admit(self, robot: str, topic: str, value: SensorValue) -> bool:
        """True if the reading must reach planning, False if it is discarded as a duplicate."""
        return self.slot(robot, topic).admit(value)

    def forget(self, robot: str) -> None:
        """Drop a robot's cached values (it left; its next incarnation starts afresh)."""
        for (owner, _), slot in self.counters.items():
            if owner == robot:
                slot.has_value = False
