"""Percentiles as numpy computes them, and windows drained under one lock, folded outside it."""

from __future__ import annotations

import random

import numpy as np
import pytest

from arpz.percentiles import Distribution, percentile, percentiles


@pytest.mark.parametrize("n", [1, 2, 3, 10, 50, 2048, 2049, 10_000])
def test_small_and_large_inputs_agree_with_numpy(n: int) -> None:
    rng = random.Random(n)
    values = [rng.uniform(-5, 100) for _ in range(n)]
    qs = (0.0, 25.0, 50.0, 99.0, 99.9, 100.0)
    expected = [float(v) for v in np.percentile(values, qs)]
    assert percentiles(values, qs) == pytest.approx(expected, rel=1e-12, abs=1e-12)
    assert percentiles(np.asarray(values), qs) == pytest.approx(expected, rel=1e-12, abs=1e-12)
    assert percentile(values, 99) == pytest.approx(expected[3], rel=1e-12, abs=1e-12)
    assert percentiles([], qs) == [None] * len(qs)


def test_a_drained_window_reaches_the_reservoir_only_when_folded() -> None:
    d = Distribution(capacity=100)
    for value in range(10):
        d.add(float(value))
    window = d.drain_window()
    assert window == [float(v) for v in range(10)]
    d.add(99.0)  # added while the drained window is being folded elsewhere
    d.fold_window(window)
    assert sorted(d.sample()) == [*map(float, range(10)), 99.0]
    assert d.total == 11 and d.max == 99.0
