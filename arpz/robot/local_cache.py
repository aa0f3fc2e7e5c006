"""The robot-side local cache of seed 001 section 2.2 (Fig. 3).

A reading equal to the last one SENT on the topic is held back; floats may be compared with a
tolerance. So that a silent topic can be told apart from a dead one, an unchanged value is sent
anyway once ``max_silence_s`` has passed since the last send (a "refresh"). Pure logic: the
caller passes the time.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from arpz.core.messages import same_value


@dataclass
class LocalCacheCounters:
    produced: int = 0
    sent: int = 0
    held_back: int = 0
    #: sends of an unchanged value because max_silence_s had passed (included in ``sent``)
    refreshes: int = 0


class LocalCache:
    def __init__(
        self,
        *,
        enabled: bool = True,
        tolerance: float = 0.0,
        max_silence_s: float = 1.0,
        same: Callable[[object, object], bool] | None = None,
    ) -> None:
        """``same``: what "unchanged" means for this topic (a typed topic's messages compared
        whole, header stamp excluded, with its deadbands); by default ``same_value`` within
        ``tolerance``."""
        if tolerance < 0 or max_silence_s <= 0:
            raise ValueError("tolerance must be >= 0 and max_silence_s > 0")
        self.enabled = enabled
        self.tolerance = tolerance
        self._same = same
        self.max_silence_s = max_silence_s
        self.counters = LocalCacheCounters()
        self._last_value: object = None
        self._last_sent_s = 0.0
        self._has_last = False

    @property
    def holding(self) -> bool:
        """A last value is cached (the next equal reading would be held back)."""
        return self.enabled and self._has_last

    def forget(self) -> None:
        """The last value offered could not be sent after all: send the next reading anyway."""
        self._has_last = False

    def offer(self, value: object, now_s: float) -> bool:
        """Count one produced reading; return True if it must be sent, False if held back."""
        counters = self.counters
        counters.produced += 1
        if self.enabled and self._has_last and self._unchanged(value):
            if now_s - self._last_sent_s < self.max_silence_s:
                counters.held_back += 1
                return False
            counters.refreshes += 1
        else:
            # a changed value (or the first one) is cached as it was sent, so a slow drift
            # within the tolerance cannot creep away from what the receiver holds
            self._last_value = value
            self._has_last = True
        self._last_sent_s = now_s
        counters.sent += 1
        return True

    def _unchanged(self, value: object) -> bool:
        return self.same(value, self._last_value)

    def same(self, a: object, b: object) -> bool:
        """Whether two readings count as one value here (the sensor's tolerance or deadbands)."""
        if self._same is not None:
            return self._same(a, b)
        return same_value(a, b, self.tolerance)  # type: ignore[arg-type]
