"""Latency distributions with bounded memory: an exact window plus a uniform reservoir.

Per-interval figures (what the dashboard plots) come from the window, which is cleared on every
``take_window``; whole-run figures (the summary's p50/p99) come from a reservoir of at most
``capacity`` values (Vitter's algorithm R), so a week-long run does not grow without bound.
"""

from __future__ import annotations

import random

import numpy as np


def percentile(values: list[float] | np.ndarray, q: float) -> float | None:
    if len(values) == 0:
        return None
    return float(np.percentile(np.asarray(values, dtype=float), q))


class Distribution:
    def __init__(self, capacity: int = 100_000, seed: int = 0) -> None:
        self.capacity = capacity
        self.count = 0
        self.max: float | None = None
        self._reservoir: list[float] = []
        self._window: list[float] = []
        self._rng = random.Random(seed)

    def add(self, value: float) -> None:
        self.count += 1
        if self.max is None or value > self.max:
            self.max = value
        self._window.append(value)
        if len(self._reservoir) < self.capacity:
            self._reservoir.append(value)
        else:
            slot = self._rng.randrange(self.count)
            if slot < self.capacity:
                self._reservoir[slot] = value

    def take_window(self) -> list[float]:
        window, self._window = self._window, []
        return window

    def sample(self) -> list[float]:
        """The reservoir: a uniform sample of every value added (all of them while below capacity)."""
        return list(self._reservoir)

    def quantile(self, q: float) -> float | None:
        return percentile(self._reservoir, q)
