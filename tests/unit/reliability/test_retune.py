"""A QoS assignment changes a writer's depth and deadline in place."""

import pytest

from arpz.channel import QOS_DEFAULT, FakeClock, QosProfile, WriterMachine
from arpz.channel.io import Inlet, Outlet
from arpz.core.protocol.actions import Notify, Send
from arpz.core.protocol.events import DeadlineMissedStatus
from arpz.transport.memory import MemoryBus, MemoryTransport


def machine() -> tuple[WriterMachine, FakeClock]:
    clock = FakeClock()
    return WriterMachine("arpz/f/robot/r1/sensor/pir", QOS_DEFAULT, b"\x01" * 8, clock), clock


def test_a_smaller_depth_keeps_the_newest_and_the_same_guid() -> None:
    writer, _ = machine()
    for i in range(10):
        writer.write(b"%d" % i)
    guid = writer.guid
    writer.retune(depth=4, deadline_s=0.0)
    assert sorted(writer.history) == [7, 8, 9, 10]
    assert writer.guid == guid and writer.qos.depth == 4
    for i in range(3):
        writer.write(b"x%d" % i)
    assert sorted(writer.history) == [10, 11, 12, 13]


def test_the_new_deadline_is_checked() -> None:
    writer, clock = machine()
    writer.retune(depth=10, deadline_s=0.1)
    writer.write(b"a")
    clock.advance(0.35)
    missed = [a for a in writer.tick() if isinstance(a, Notify) and a.event == "deadline"]
    assert missed and isinstance(missed[0].status, DeadlineMissedStatus)
    assert missed[0].status.total_count == 3


def test_an_invalid_depth_is_refused() -> None:
    writer, _ = machine()
    with pytest.raises(ValueError):
        writer.retune(depth=0, deadline_s=0.0)


def test_the_qos_in_force_lives_in_one_place_and_every_view_of_it_follows_retune() -> None:
    """Issue 16: ``Writer.qos`` was set once and never updated by ``retune``; the QoS in force
    now lives in the machine and the Outlet, the Writer and the Inlet, the Reader read it."""
    bus = MemoryBus()
    outlet = Outlet(MemoryTransport(bus), "t/x", QosProfile(depth=10))
    inlet = Inlet(MemoryTransport(bus), "t/x", QosProfile(depth=10), lambda k, p: None)
    try:
        outlet.retune(depth=3, deadline_s=0.5)
        inlet.reader.retune(depth=3)  # type: ignore[union-attr]
        assert outlet.writer is not None and inlet.reader is not None
        for qos in (outlet.qos, outlet.writer.qos, inlet.qos, inlet.reader.qos):
            assert qos is not None and qos.depth == 3, qos
        assert outlet.qos is not None and outlet.qos.deadline_s == 0.5
        plain = Outlet(MemoryTransport(bus), "t/y", None)
        assert plain.qos is None
        plain.close()
    finally:
        outlet.close()
        inlet.close()


def _heartbeats(actions: list[object]) -> int:
    return sum(1 for a in actions if isinstance(a, Send) and "/hb/" in a.key)


def test_a_shorter_heartbeat_period_paces_the_next_heartbeats_at_once() -> None:
    """The closed QoS loop shortens the heartbeat on a lossy link: the writer must not wait out
    the 0.1 s period already scheduled, and None keeps the period in force."""
    writer, clock = machine()
    writer.write(b"a")
    writer.tick()  # the first heartbeat goes at once; the next one is due 0.1 s later
    writer.retune(depth=10, deadline_s=0.0, heartbeat_period_s=0.02)
    assert writer.qos.heartbeat_period_s == 0.02
    sent = 0
    for i in range(10):  # 0.1 s of a streaming topic in 10 ms steps: a heartbeat every 20 ms
        clock.advance(0.01)
        writer.write(b"%d" % i)
        sent += _heartbeats(writer.tick())
    assert sent == 5
    writer.retune(depth=10, deadline_s=0.0)
    assert writer.qos.heartbeat_period_s == 0.02
    with pytest.raises(ValueError):
        writer.retune(depth=10, deadline_s=0.0, heartbeat_period_s=0.0)
