"""The CEDDP's command writers: one per robot and command, bounded per robot, and every command
either written or counted."""

from arpz.ceddp.downlink import Downlink
from arpz.core.config import CeddpConfig
from arpz.transport.memory import MemoryBus, MemoryTransport


def test_a_robot_cannot_make_the_ceddp_open_unbounded_writers() -> None:
    downlink = Downlink(MemoryTransport(MemoryBus()), "f", CeddpConfig(), max_per_robot=3)
    try:
        downlink.open_robot("r1", [f"c{i}" for i in range(10)])
        counters = downlink.snapshot()
        assert sorted(name for robot, name in counters) == ["c0", "c1", "c2"]
        assert downlink.over_limit == {"r1": 7}
        # beyond the bound a command is refused and counted, never lost silently
        downlink.send("r1", "c9", b"x")
        downlink.send("r1", "c0", b"x")
        after = downlink.snapshot()
        assert after[("r1", "c9")].refused == 1
        assert after[("r1", "c0")].written == 1 and after[("r1", "c0")].unmatched == 1
    finally:
        downlink.close()
