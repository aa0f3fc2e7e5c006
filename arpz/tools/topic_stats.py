"""The statistics of ``arpz topic hz``, ``bw`` and ``delay``: sliding windows over the last N
messages, as ``ros2 topic hz/bw/delay`` keep them. Pure: times and sizes in, figures out."""

from __future__ import annotations

import itertools
import math
from collections import deque
from dataclasses import dataclass

#: ``ros2 topic hz``'s default window
DEFAULT_WINDOW = 10_000


@dataclass(frozen=True)
class Spread:
    """Mean, min, max and standard deviation (population) of a window of values."""

    mean: float
    min: float
    max: float
    std: float
    n: int

    @classmethod
    def of(cls, values: list[float]) -> Spread | None:
        if not values:
            return None
        mean = math.fsum(values) / len(values)
        var = math.fsum((v - mean) ** 2 for v in values) / len(values)
        return cls(mean, min(values), max(values), math.sqrt(var), len(values))


class RateWindow:
    """Arrival times of the last ``window`` messages: the rate is 1 / the mean period, with the
    min, max and std dev of the periods (``ros2 topic hz``)."""

    def __init__(self, window: int = DEFAULT_WINDOW) -> None:
        if window < 2:
            raise ValueError(f"the window must hold at least 2 messages, got {window}")
        self._times: deque[float] = deque(maxlen=window)
        self.total = 0

    def add(self, arrival_s: float) -> None:
        self._times.append(arrival_s)
        self.total += 1

    def periods(self) -> Spread | None:
        times = list(self._times)
        return Spread.of([b - a for a, b in itertools.pairwise(times)])

    def rate_hz(self) -> float | None:
        spread = self.periods()
        if spread is None or spread.mean <= 0:
            return None
        return 1.0 / spread.mean


class SizeWindow:
    """Sizes and arrival times of the last ``window`` messages: bytes per second, and the mean,
    min and max size (``ros2 topic bw``)."""

    def __init__(self, window: int = DEFAULT_WINDOW) -> None:
        if window < 1:
            raise ValueError(f"the window must hold at least 1 message, got {window}")
        self._items: deque[tuple[float, int]] = deque(maxlen=window)
        self.total = 0
        self.total_bytes = 0

    def add(self, arrival_s: float, size: int) -> None:
        self._items.append((arrival_s, size))
        self.total += 1
        self.total_bytes += size

    def sizes(self) -> Spread | None:
        return Spread.of([float(size) for _, size in self._items])

    def bytes_per_s(self) -> float | None:
        """The bytes that arrived after the window's first message, over the time since it:
        unbiased for short windows (``ros2 topic bw`` divides the whole window's bytes by the time
        since its first arrival, which overstates a slow topic's rate)."""
        if len(self._items) < 2:
            return None
        span = self._items[-1][0] - self._items[0][0]
        if span <= 0:
            return None
        return sum(size for _, size in list(self._items)[1:]) / span


class ValueWindow:
    """The last ``window`` values (delays in seconds, for ``topic delay``)."""

    def __init__(self, window: int = DEFAULT_WINDOW) -> None:
        if window < 1:
            raise ValueError(f"the window must hold at least 1 value, got {window}")
        self._values: deque[float] = deque(maxlen=window)
        self.total = 0

    def add(self, value: float) -> None:
        self._values.append(value)
        self.total += 1

    def spread(self) -> Spread | None:
        return Spread.of(list(self._values))


def human_bytes(n: float) -> str:
    """``ros2 topic bw`` style: B, KB, MB (powers of 1000)."""
    for unit, scale in (("MB", 1e6), ("KB", 1e3)):
        if abs(n) >= scale:
            return f"{n / scale:.2f} {unit}"
    return f"{n:.0f} B"
