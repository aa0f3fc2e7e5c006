import itertools

from hypothesis import given
from hypothesis import strategies as st

from arpz.robot.local_cache import LocalCache

values = st.one_of(
    st.floats(allow_nan=False, width=32), st.booleans(), st.sampled_from(["detect", "not detect"])
)


def test_identical_readings_are_held_back_until_max_silence() -> None:
    cache = LocalCache(max_silence_s=1.0)
    assert cache.offer(1.5, 0.0)
    assert not cache.offer(1.5, 0.1)
    assert not cache.offer(1.5, 0.99)
    assert cache.offer(1.5, 1.0)  # silent for max_silence_s: refresh
    assert not cache.offer(1.5, 1.5)
    assert cache.offer(1.6, 1.6)
    c = cache.counters
    assert (c.produced, c.sent, c.held_back, c.refreshes) == (6, 3, 3, 1)


def test_tolerance_compares_with_the_last_sent_value_so_drift_cannot_creep() -> None:
    cache = LocalCache(tolerance=0.05, max_silence_s=100)
    assert cache.offer(1.00, 0)
    assert not cache.offer(1.04, 1)
    assert not cache.offer(1.049, 2)
    assert cache.offer(1.06, 3)  # 0.06 from what was sent, although 0.01 from the previous


def test_type_matters_true_is_not_one() -> None:
    cache = LocalCache(max_silence_s=100)
    assert cache.offer(1.0, 0)
    assert cache.offer(True, 1)
    assert cache.offer("detect", 2)
    assert not cache.offer("detect", 3)


def test_disabled_cache_sends_everything() -> None:
    cache = LocalCache(enabled=False)
    assert all(cache.offer(2.0, t / 10) for t in range(10))
    assert cache.counters.held_back == 0


@given(st.lists(values, max_size=200), st.floats(min_value=0.01, max_value=5))
def test_counts_add_up_and_no_two_consecutive_sends_are_equal_within_silence(
    readings: list[float | bool | str], max_silence_s: float
) -> None:
    cache = LocalCache(max_silence_s=max_silence_s)
    sent: list[tuple[float, float | bool | str]] = []
    for i, value in enumerate(readings):
        now = i * 0.01
        if cache.offer(value, now):
            sent.append((now, value))
    c = cache.counters
    assert c.produced == len(readings) == c.sent + c.held_back
    assert c.sent == len(sent)
    for (t0, v0), (t1, v1) in itertools.pairwise(sent):
        if type(v0) is type(v1) and v0 == v1:
            assert t1 - t0 >= max_silence_s - 1e-9
