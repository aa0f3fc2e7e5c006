import pytest

from arpz.mission.clock import ManualTime, SimClock


def test_sim_clock_follows_its_time_source_from_zero() -> None:
    source = ManualTime(start_s=1000.0)
    clock = SimClock(source)
    assert clock.now_s() == 0.0
    source.advance(2.5)
    assert clock.now_s() == pytest.approx(2.5)


def test_tick_hands_out_each_elapsed_interval_once() -> None:
    source = ManualTime()
    clock = SimClock(source)
    source.advance(0.1)
    assert clock.tick() == pytest.approx(0.1)
    assert clock.tick() == 0.0
    source.advance(0.75)  # a late loop: the whole gap, not a capped step
    assert clock.tick() == pytest.approx(0.75)


def test_manual_time_cannot_go_backwards() -> None:
    with pytest.raises(ValueError, match="backwards"):
        ManualTime().advance(-1.0)
