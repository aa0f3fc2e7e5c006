"""The CEDDP freezes its start-up objects out of the collector's full passes, and only those."""

from __future__ import annotations

import gc
import weakref

from arpz.ceddp.__main__ import freeze_start_up


class Node:
    def __init__(self) -> None:
        self.other: Node | None = None


def test_start_up_objects_are_frozen_and_later_garbage_is_still_collected() -> None:
    before = Node()
    try:
        freeze_start_up()
        assert gc.get_freeze_count() > 0
        walked = {id(o) for o in gc.get_objects()}  # every generation the collector walks
        assert id(before) not in walked
        # a cycle made after start-up is garbage the full passes still find
        a, b = Node(), Node()
        a.other, b.other = b, a
        gone = weakref.ref(a)
        del a, b
        gc.collect()
        assert gone() is None
    finally:
        gc.unfreeze()
