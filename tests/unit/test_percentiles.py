"""Percentiles as numpy computes them; windows drained under one lock, folded outside it; and
whole-run figures from a log histogram, within its relative error of numpy's on the values."""

from __future__ import annotations

import random

import numpy as np
import pytest

from arpz.core.percentiles import (
    _FOLD_AT,
    RELATIVE_ERROR,
    Distribution,
    LogHistogram,
    percentile,
    percentiles,
)

QS = (0.0, 1.0, 25.0, 50.0, 99.0, 99.9, 100.0)


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


def within_relative_error(got: list[float | None], values: np.ndarray) -> None:
    """Every figure within the histogram's error of numpy's: a value read from a bucket is
    within RELATIVE_ERROR of each value in it, and an interpolation between two such values
    within it of the interpolation between the true ones."""
    expected = np.percentile(values, QS)
    for q, g, e in zip(QS, got, expected, strict=True):
        assert g is not None
        assert abs(g - e) <= RELATIVE_ERROR * max(abs(e), 1e-4) * 1.001 + 1e-4, (q, g, e)


@pytest.mark.parametrize(
    "values",
    [
        np.random.default_rng(1).lognormal(0.0, 1.5, 50_000),  # latencies, ms
        np.random.default_rng(2).uniform(-5.0, 100.0, 10_000),  # staleness on a corrected clock
        np.random.default_rng(3).exponential(0.05, 3_000),  # sub-millisecond, down to ~0
        np.array([0.0, 0.0, -1e-9, 3e-6, 250.0]),  # zeros and magnitudes below the lowest bucket
    ],
    ids=["lognormal", "both-signs", "sub-ms", "zeros"],
)
def test_histogram_figures_are_within_the_relative_error_of_numpys(values: np.ndarray) -> None:
    h = LogHistogram()
    for chunk in np.array_split(values, 7):  # folded in windows, as the metrics tick does
        h.add_values(chunk)
    assert h.total == len(values)
    got = h.quantiles(QS)
    within_relative_error(got, values)
    # the extremes are kept exactly
    assert got[0] == float(values.min()) and got[-1] == float(values.max())


def test_equal_values_and_a_single_value_come_back_exactly() -> None:
    h = LogHistogram()
    assert h.quantiles((50.0,)) == [None]
    h.add_values(np.array([7.3]))
    assert h.quantiles((0.0, 50.0, 99.0, 100.0)) == [7.3] * 4
    h.add_values(np.full(99, 7.3))
    assert h.quantiles((0.0, 50.0, 99.0, 100.0)) == [7.3] * 4


def test_pooled_histograms_give_the_figures_of_the_values_together() -> None:
    rng = np.random.default_rng(4)
    parts = [rng.lognormal(m, 0.5, 4_000) for m in (-1.0, 0.0, 2.0)]
    histograms = []
    for part in parts:
        h = LogHistogram()
        h.add_values(part)
        histograms.append(h)
    together = LogHistogram()
    together.add_values(np.concatenate(parts))
    pooled = LogHistogram.pooled(histograms)
    assert np.array_equal(pooled.counts, together.counts)
    assert pooled.quantiles(QS) == together.quantiles(QS)
    within_relative_error(pooled.quantiles(QS), np.concatenate(parts))
    assert histograms[0].total == 4_000  # pooling copied, it did not add into a part


def test_a_drained_window_reaches_the_whole_run_only_when_folded() -> None:
    d = Distribution()
    for value in range(1, 11):
        d.add(float(value))
    window = d.drain_window()
    assert window == [float(v) for v in range(1, 11)]
    assert d.folded().total == 0 and d.total == 0
    d.add(99.0)  # added while the drained window is being folded elsewhere
    d.fold_window(window)
    assert d.folded().total == 10 and d.max == 10.0  # the late value is still in the window
    assert d.total == 11
    assert d.quantiles(0, 100) == [1.0, 99.0] and d.max == 99.0
    assert d.histogram().total == 11


def test_windows_wait_in_a_bounded_buffer_and_every_read_sees_them() -> None:
    d = Distribution()
    per_window = 50
    for _ in range(_FOLD_AT // per_window - 1):
        for _ in range(per_window):
            d.add(1.5)
        d.take_window()
    # not folded yet, but counted and read
    assert d.count == (_FOLD_AT // per_window - 1) * per_window
    assert d.quantile(50) == 1.5
    for _ in range(2 * _FOLD_AT):
        d.add(2.5)
    d.take_window()  # over the bound: folded at once
    assert not d._pending  # the buffer was emptied by the fold
    assert d.quantiles(100) == [2.5] and d.count == d.total


def test_infinities_and_nans_are_counted_never_a_crash() -> None:
    """Bad input (the ingest never makes it: its values are differences of integer clocks): an
    infinity lands in its sign's outermost bucket and is the exact extreme, a NaN is counted
    apart; before, an infinity cast to an integer index raised IndexError in the fold."""
    h = LogHistogram()
    h.add_values(np.array([1.0, 2.0, np.inf]))  # the all-positive fast path
    h.add_values(np.array([-np.inf, 0.0, np.nan, 3.0]))  # the general path
    assert h.total == 6 and h.not_numbers == 1
    assert h.quantiles((0.0, 100.0)) == [-np.inf, np.inf]
    assert h.quantiles((50.0,)) == [pytest.approx(1.5, rel=RELATIVE_ERROR)]
    pooled = LogHistogram.pooled([h, h.copy()])
    assert pooled.total == 12 and pooled.not_numbers == 2
    d = Distribution()
    for value in (float("nan"), 5.0, 7.0):  # a NaN first made ``max`` return it
        d.add(value)
    d.take_window()
    assert d.max == 7.0 and d.quantiles(0, 100) == [5.0, 7.0]
    d.add(float("inf"))
    assert d.quantiles(100) == [float("inf")] and d.max == float("inf")


def test_weighted_values_count_as_that_many_equal_values() -> None:
    rng = np.random.default_rng(7)
    values = rng.lognormal(0.0, 1.0, 300)
    weights = rng.integers(1, 40, 300)
    weighted = LogHistogram()
    weighted.add_values(values, weights)
    repeated = LogHistogram()
    repeated.add_values(np.repeat(values, weights))
    assert weighted.total == int(weights.sum())
    assert np.array_equal(weighted.counts, repeated.counts)
    assert weighted.quantiles((50, 99)) == repeated.quantiles((50, 99))
    nan = LogHistogram()
    nan.add_values(np.array([1.0, float("nan")]), np.array([3, 5]))
    assert (nan.total, nan.not_numbers) == (3, 5)


@pytest.mark.parametrize(
    "weights", [np.array([1, 2]), np.array([1, -1, 1])], ids=["short", "negative"]
)
def test_bad_weights_are_refused_before_anything_is_counted(weights: np.ndarray) -> None:
    histogram = LogHistogram()
    with pytest.raises(ValueError, match="non-negative counts"):
        histogram.add_values(np.array([1.0, 2.0, 3.0]), weights)
    assert histogram.total == 0 and histogram.low is None
