"""A writer's identity is bound to the key it writes (issue 15, item 1).

robot2 may put on ``robot/robot2/...`` only (the router's access control), but it can read
robot1's writer guid from a liveliness token. Every message it forges on its own keys with that
guid must be refused and counted as an impersonation, and robot1's stream stay exact.
"""

from __future__ import annotations

import random

from arpz.core.protocol import wire
from arpz.core.protocol._common import new_guid
from arpz.core.protocol.actions import Send
from arpz.core.protocol.qos import QosProfile
from arpz.core.protocol.reader_machine import ReaderMachine
from arpz.core.protocol.timers import FakeClock
from arpz.core.protocol.writer_machine import WriterMachine
from tests.unit.reliability.lossy_bus import Link, LossyBus, Node

VICTIM = "robot/robot1/imu"
ATTACKER = "robot/robot2/imu"
QOS = QosProfile(depth=100)


def fleet() -> tuple[LossyBus, Node, Node, WriterMachine]:
    clock = FakeClock()
    bus = LossyBus(random.Random(1), Link(), clock)
    reader = bus.add(ReaderMachine("robot/*/imu", QOS, new_guid(), clock))
    victim = bus.add(WriterMachine(VICTIM, QOS, new_guid(), clock))
    bus.run_for(0.05)
    assert isinstance(victim.machine, WriterMachine)
    return bus, reader, victim, victim.machine


def received(reader: Node) -> list[int]:
    return [info.seq for _, info in reader.delivered]


def write_some(bus: LossyBus, victim: Node, n: int) -> None:
    for i in range(n):
        bus.write(victim, b"%d" % i)
        bus.run_for(0.01)


def machine(node: Node) -> ReaderMachine:
    assert isinstance(node.machine, ReaderMachine)
    return node.machine


def test_data_with_another_keys_writer_guid_is_refused() -> None:
    bus, reader, victim, w = fleet()
    write_some(bus, victim, 10)
    for seq in (11, 10**6, 2**62):  # the next seq, a huge jump, the edge of the range
        bus.send(Send(ATTACKER, b"forged", wire.encode_data(0, w.guid, seq, 0)))
    bus.run_for(0.05)
    write_some(bus, victim, 10)
    bus.run_for(0.5)
    r = machine(reader)
    assert received(reader) == list(range(1, 21))
    assert r.lost == 0 and r.impersonations == 3
    assert r.stats().bad_input >= 3 and r.stats().impersonations == 3


def test_forged_heartbeats_and_gaps_on_own_keys_are_refused() -> None:
    bus, reader, victim, w = fleet()
    write_some(bus, victim, 5)
    r = machine(reader)
    # a heartbeat on robot2's key claiming robot1's writer has written up to 10**6
    hb = wire.encode_heartbeat(0, w.guid, 1, 10**6, 1)
    bus.send(Send(wire.heartbeat_key(ATTACKER, w.hex), hb))
    # the same, on robot2's key with robot2's guid in the key but robot1's in the message
    bus.send(Send(wire.heartbeat_key(ATTACKER, new_guid().hex()), hb))
    # GAPs directed at the reader on robot2's key: "robot1's 1 .. 10**6 are gone"
    gap = wire.encode_gap(w.guid, r.guid, [(1, 10**6)])
    for _ in range(5):
        bus.send(Send(wire.directed_key(ATTACKER, r.hex), gap))
    # and a resend with robot1's guid
    bus.send(Send(wire.directed_key(ATTACKER, r.hex), b"x", wire.encode_data(1, w.guid, 6, 0)))
    bus.run_for(0.1)
    write_some(bus, victim, 5)
    bus.run_for(0.5)
    assert received(reader) == list(range(1, 11))
    assert r.lost == 0 and r.gaps == 0
    assert r.impersonations == 8


def test_a_forged_token_with_the_victims_guid_does_not_block_it() -> None:
    """robot2 declares a writer token on its own key with robot1's guid before robot1's writer
    appears: the two are different writers (key, guid), robot1 still matches and delivers."""
    clock = FakeClock()
    bus = LossyBus(random.Random(2), Link(), clock)
    reader = bus.add(ReaderMachine("robot/*/imu", QOS, new_guid(), clock))
    guid = new_guid()
    forged = WriterMachine(ATTACKER, QOS, guid, clock)
    bus.add(forged)
    bus.run_for(0.05)
    victim = bus.add(WriterMachine(VICTIM, QOS, guid, clock))
    bus.run_for(0.05)
    write_some(bus, victim, 10)
    bus.run_for(0.5)
    assert received(reader) == list(range(1, 11))
    assert {topic for topic, _ in machine(reader).writers} == {VICTIM, ATTACKER}


def test_acknack_with_another_readers_guid_is_refused() -> None:
    clock = FakeClock()
    w = WriterMachine(VICTIM, QOS, new_guid(), clock)
    reader, other = new_guid(), new_guid()
    w.on_reader_token(wire.reader_token(VICTIM, reader.hex(), "RVA_0_0"), True)
    w.write(b"1")
    forged = wire.encode_acknack(reader, w.guid, 2, 1, [])
    assert w.on_acknack(wire.acknack_key(VICTIM, w.hex, other.hex()), forged, None) == []
    assert w.bad.counts["ACKNACK with another guid than its key's reader"] == 1
    assert w.acknowledged_through() == 0


def test_writer_tokens_are_bounded_per_key_and_in_all() -> None:
    """A client inventing writer guids (on its own keys) cannot grow a reader without bound."""
    from arpz.core.protocol.reader_machine import MAX_WRITERS_PER_KEY

    clock = FakeClock()
    r = ReaderMachine("robot/*/imu", QOS, new_guid(), clock, max_writers=40)
    for _ in range(100):  # one key, invented guids
        r.on_writer_token(wire.writer_token(ATTACKER, new_guid().hex(), "RVA_0_0"), True)
    assert len(r.writers) == MAX_WRITERS_PER_KEY and r.writers_refused == 100 - MAX_WRITERS_PER_KEY
    for i in range(100):  # invented keys
        r.on_writer_token(wire.writer_token(f"robot/r{i}/imu", new_guid().hex(), "RVA_0_0"), True)
    assert len(r.writers) == 40 and r.stats().writers_refused == 100 - 16 + 100 - 24
