"""The CEDDP's control queue: the latest per key, bounded, first come first served."""

from __future__ import annotations

import threading

import pytest

from arpz.ceddp.control_queue import ControlQueue


def test_a_flooded_key_keeps_one_slot_and_its_place() -> None:
    q = ControlQueue(limit=10)
    q.put(1, "robot/r9/stats", b"first")
    q.put(1, "robot/r1/stats", b"r1")
    for i in range(10_000):
        q.put(1, "robot/r9/stats", b"%d" % i)
    q.put(2, "robot/r9/stats", b"presence")  # another kind of the same key: its own slot
    assert len(q) == 3 and q.coalesced == 10_000
    assert q.get() == (1, "robot/r9/stats", b"9999")  # the latest, in the first one's place
    assert q.get() == (1, "robot/r1/stats", b"r1")
    assert q.get() == (2, "robot/r9/stats", b"presence")


def test_distinct_keys_beyond_the_limit_are_refused_and_counted() -> None:
    q = ControlQueue(limit=2)
    assert q.put(1, "a", b"") and q.put(1, "b", b"")
    assert not q.put(1, "c", b"") and not q.put(3, "d", b"")
    assert q.put(1, "a", b"again")  # a waiting key is still replaced
    assert q.dropped == {1: 1, 3: 1} and q.peak == 2
    with pytest.raises(ValueError):
        ControlQueue(limit=0)


def test_close_drains_then_ends_the_worker() -> None:
    q = ControlQueue(limit=100)
    got: list[object] = []

    def worker() -> None:
        while (item := q.get()) is not None:
            got.append(item)

    thread = threading.Thread(target=worker)
    thread.start()
    for i in range(50):
        q.put(1, f"k{i}", b"")
    q.close()
    thread.join(timeout=5)
    assert not thread.is_alive() and len(got) == 50
