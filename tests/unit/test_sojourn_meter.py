"""A delivery pass's samples are counted with its oldest sample's time in the process."""

from __future__ import annotations

import numpy as np

from arpz.core.percentiles import RELATIVE_ERROR
from arpz.core.protocol import timers
from arpz.core.protocol.timers import SojournMeter


def test_each_sample_of_a_pass_counts_with_the_pass_s_figure() -> None:
    meter = SojournMeter()
    meter.observe(1_000_000, 99)  # 99 samples in passes of 1 ms
    meter.observe(50_000_000, 1)  # one pass of a single sample, 50 ms
    p50, p99 = meter.quantiles_ms(50, 99)
    assert p50 is not None and abs(p50 - 1.0) <= RELATIVE_ERROR
    # the 99th percentile of 100 samples interpolates between the 99th and the 100th
    assert p99 is not None and 1.0 < p99 < 50.0
    assert meter.worst_ms == 50.0 and meter.samples == 100
    # a pass of 512 samples weighs 512 times a pass of one
    meter.observe(80_000_000, 512)
    (p50,) = meter.quantiles_ms(50)
    assert p50 is not None and abs(p50 - 80.0) <= 80.0 * RELATIVE_ERROR


def test_untimed_passes_are_counted_apart_and_an_empty_meter_says_none() -> None:
    meter = SojournMeter()
    meter.observe(None, 7)
    meter.observe(2_000_000, 0)  # a pass that delivered nothing counts nothing
    assert meter.quantiles_ms(50, 99) == [None, None]
    assert meter.worst_ms is None
    assert (meter.samples, meter.unknown_samples) == (0, 7)


def test_passes_fold_into_the_histogram_in_bounded_batches() -> None:
    meter = SojournMeter()
    for i in range(timers._SOJOURN_FOLD_AT + 10):
        meter.observe((i % 10 + 1) * 1_000_000, 2)
    assert len(meter._values) == 10  # the rest were folded
    p50, p99 = meter.quantiles_ms(50, 99)
    exact = np.percentile(np.repeat((np.arange(timers._SOJOURN_FOLD_AT + 10) % 10 + 1.0), 2), 50)
    assert p50 is not None and abs(p50 - exact) <= exact * RELATIVE_ERROR + 1e-9
    assert len(meter._values) == 0 and meter.samples == 2 * (timers._SOJOURN_FOLD_AT + 10)
    assert p99 is not None and abs(p99 - 10.0) <= 10.0 * RELATIVE_ERROR
