"""The windows of topic hz, bw and delay: figures from known arrival times and sizes."""

from __future__ import annotations

import math

import pytest

from arpz.tools.topic_stats import RateWindow, SizeWindow, Spread, ValueWindow, human_bytes


def test_rate_is_one_over_the_mean_period_with_its_spread() -> None:
    window = RateWindow(100)
    for t in (0.0, 0.1, 0.3, 0.4):  # periods 0.1, 0.2, 0.1
        window.add(t)
    periods = window.periods()
    assert periods is not None
    assert periods.n == 3
    assert (periods.min, periods.max) == pytest.approx((0.1, 0.2))
    assert periods.mean == pytest.approx(0.4 / 3)
    assert periods.std == pytest.approx(math.sqrt(2) / 30)
    assert window.rate_hz() == pytest.approx(7.5)


def test_the_rate_window_keeps_only_the_last_messages() -> None:
    window = RateWindow(3)
    for t in (0.0, 10.0, 10.5, 11.0):  # the 10 s gap falls out of a 3-message window
        window.add(t)
    assert window.rate_hz() == pytest.approx(2.0)
    assert window.total == 4


def test_no_rate_from_fewer_than_two_messages() -> None:
    window = RateWindow()
    assert window.rate_hz() is None
    window.add(1.0)
    assert window.rate_hz() is None and window.periods() is None
    with pytest.raises(ValueError, match="at least 2"):
        RateWindow(1)


def test_bandwidth_counts_the_bytes_after_the_first_message() -> None:
    window = SizeWindow(10)
    assert window.bytes_per_s() is None
    window.add(0.0, 1000)
    assert window.bytes_per_s() is None
    window.add(0.5, 1000)
    window.add(1.0, 3000)
    assert window.bytes_per_s() == pytest.approx(4000.0)
    sizes = window.sizes()
    assert sizes is not None
    assert sizes.mean == pytest.approx(5000 / 3)
    assert (sizes.min, sizes.max, sizes.n) == (1000, 3000, 3)
    assert window.total_bytes == 5000


def test_values_and_their_spread() -> None:
    window = ValueWindow(2)
    for v in (5.0, 1.0, 3.0):
        window.add(v)
    assert window.spread() == Spread(2.0, 1.0, 3.0, 1.0, 2)
    assert ValueWindow().spread() is None


@pytest.mark.parametrize(
    ("n", "text"), [(12, "12 B"), (1500, "1.50 KB"), (921_600, "921.60 KB"), (2.5e6, "2.50 MB")]
)
def test_human_bytes(n: float, text: str) -> None:
    assert human_bytes(n) == text
