"""The impairment model of ``arpz.netem``, with a seeded RNG and a given clock."""

from __future__ import annotations

import itertools
import random

import pytest

from arpz.netem.model import Direction, GilbertElliott, Impairments, Outage, frames_of


def run(
    imp: Impairments, n: int = 20000, size: int = 100, gap_s: float = 0.001
) -> tuple[Direction, list[list[float]]]:
    d = Direction(imp, random.Random(5))
    fates = [d.fate(size, i * gap_s, i * gap_s) for i in range(n)]
    return d, fates


def test_random_loss_rate_and_counters() -> None:
    d, fates = run(Impairments(loss=0.3))
    lost = sum(1 for f in fates if not f)
    assert abs(lost / 20000 - 0.3) < 0.015
    assert d.counters.dropped_loss == lost and d.counters.received == 20000


def test_gilbert_elliott_is_bursty_with_the_expected_mean() -> None:
    ge = GilbertElliott(p=0.02, r=0.2)
    _, fates = run(Impairments(burst=ge), n=50000)
    lost = [not f for f in fates]
    assert abs(sum(lost) / len(lost) - ge.mean_loss) < 0.02
    runs, cur = [], 0
    for x in lost:
        if x:
            cur += 1
        elif cur:
            runs.append(cur)
            cur = 0
    assert 4 < sum(runs) / len(runs) < 6  # mean burst 1 / r = 5


def test_outage_clean_period_duplicates_and_reordering() -> None:
    outage = Outage(start_s=1.0, duration_s=2.0)  # 2 s to 4 s after the link started
    _, fates = run(Impairments(clean_s=1.0, outages=(outage,)), n=5000)
    assert all(fates[:1999]) and not any(fates[2001:3999]) and all(fates[4001:])
    _, fates = run(Impairments(duplicate=0.5), n=2000)
    assert abs(sum(len(f) == 2 for f in fates) / 2000 - 0.5) < 0.05
    _, fates = run(Impairments(reorder=0.1, reorder_gap_s=0.005), n=2000)
    departures = [f[0] for f in fates]
    assert sum(b < a for a, b in itertools.pairwise(departures)) > 100


def test_bandwidth_cap_spaces_datagrams_and_tail_drops_beyond_the_queue_limit() -> None:
    imp = Impairments(rate_bps=80_000, queue_limit_s=0.1)  # 1000-byte datagram = 0.1 s
    d, fates = run(imp, n=50, size=1000, gap_s=0.0)
    sent = [f[0] for f in fates if f]
    assert sent[:2] == pytest.approx([0.1, 0.2])
    assert d.counters.dropped_queue == 48


@pytest.mark.parametrize("kwargs", [{"loss": 1.5}, {"delay_s": -1.0}, {"duplicate": -0.1}])
def test_bad_settings_are_refused(kwargs: dict[str, float]) -> None:
    with pytest.raises(ValueError):
        Impairments(**kwargs)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="r must be > 0"):
        GilbertElliott(p=0.1, r=0.0)


@pytest.mark.parametrize(
    ("size", "frames"), [(0, 1), (1, 1), (1472, 1), (1473, 2), (2952, 2), (2953, 3), (8192, 6)]
)
def test_a_datagram_takes_the_frames_ip_fragmentation_gives_it(size: int, frames: int) -> None:
    assert frames_of(size) == frames
    assert frames_of(size, frame_bytes=9000) == 1


@pytest.mark.parametrize(("size", "loss"), [(1000, 0.1), (8192, 0.1), (921_600 // 64, 0.01)])
def test_per_frame_loss_loses_a_datagram_when_any_of_its_frames_is_lost(
    size: int, loss: float
) -> None:
    d, fates = run(Impairments(loss=loss, per_frame=True), n=20000, size=size)
    expected = 1 - (1 - loss) ** frames_of(size)
    lost = sum(1 for f in fates if not f)
    assert abs(lost / 20000 - expected) < 4 * (expected * (1 - expected) / 20000) ** 0.5 + 1e-3
    c = d.counters
    assert c.dropped_loss == lost and c.frames_in == 20000 * frames_of(size)
    assert c.bytes_in == 20000 * size and c.bytes_out == (20000 - lost) * size
    assert c.largest_datagram == size


def test_per_frame_loss_leaves_one_frame_datagrams_as_per_datagram_loss_decides_them() -> None:
    _, per_datagram = run(Impairments(loss=0.2), size=1472)
    _, per_frame = run(Impairments(loss=0.2, per_frame=True), size=1472)
    assert per_frame == per_datagram
    # without per_frame a large datagram is lost at the datagram rate, whatever its size
    _, fates = run(Impairments(loss=0.2), size=60_000)
    assert abs(sum(1 for f in fates if not f) / 20000 - 0.2) < 0.015


def test_a_frame_smaller_than_an_ipv4_mtu_is_refused() -> None:
    with pytest.raises(ValueError, match="frame_bytes"):
        Impairments(frame_bytes=20)
