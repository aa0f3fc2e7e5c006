from arpz.ceddp.cache_control import CacheControl


def test_identical_reading_is_discarded_per_robot_and_topic() -> None:
    cc = CacheControl()
    assert cc.admit("r1", "pir", "detect")
    assert not cc.admit("r1", "pir", "detect")
    assert cc.admit("r2", "pir", "detect")  # other robot, own cache
    assert cc.admit("r1", "light", "detect")  # other topic, own cache
    assert cc.admit("r1", "pir", "not detect")
    assert cc.admit("r1", "pir", "detect")
    assert (cc.counters[("r1", "pir")].hits, cc.counters[("r1", "pir")].misses) == (1, 3)


def test_false_is_a_value_and_types_are_compared() -> None:
    cc = CacheControl()
    assert cc.admit("r1", "flame", False)
    assert not cc.admit("r1", "flame", False)
    assert cc.admit("r1", "flame", 0.0)


def test_forget_and_disabled() -> None:
    cc = CacheControl()
    cc.admit("r1", "t", 1.0)
    cc.forget("r1")
    assert cc.admit("r1", "t", 1.0)
    off = CacheControl(enabled=False)
    assert off.admit("r1", "t", 1.0) and off.admit("r1", "t", 1.0)
    assert off.counters[("r1", "t")].hits == 0
