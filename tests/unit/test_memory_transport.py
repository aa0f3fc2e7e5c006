import pytest

from arpz.core.transport import TransportError
from arpz.transport.memory import MemoryBus, MemoryTransport, key_matches


def test_key_matching_follows_zenoh_wildcards() -> None:
    assert key_matches("arpz/f/robot/*/sensor/*", "arpz/f/robot/r1/sensor/pir")
    assert not key_matches("arpz/f/robot/*/sensor/*", "arpz/f/robot/r1/stats")
    assert key_matches("arpz/**", "arpz/f/robot/r1/stats")
    assert key_matches("arpz/f/**", "arpz/f")
    assert not key_matches("arpz/f/*", "arpz/f/a/b")


def test_put_reaches_matching_subscribers_and_liveliness_is_reported() -> None:
    bus = MemoryBus()
    a, b = MemoryTransport(bus), MemoryTransport(bus)
    got: list[tuple[str, bytes, bytes | None]] = []
    alive: list[tuple[str, bool]] = []
    b.subscribe("x/*", lambda k, p, att: got.append((k, p, att)))
    token = a.declare_token("p/a")
    b.watch_liveliness("p/*", lambda k, up: alive.append((k, up)))
    a.put("x/1", b"one", attachment=b"h")
    a.put("y/1", b"two")
    token.undeclare()
    assert got == [("x/1", b"one", b"h")]
    assert alive == [("p/a", True), ("p/a", False)]
    a.close()
    b.close()


def test_a_publisher_matches_only_while_a_subscriber_covers_its_key() -> None:
    bus = MemoryBus()
    robot, server = MemoryTransport(bus), MemoryTransport(bus)
    publisher = robot.publisher("arpz/f/robot/e2/sensor/pir")
    assert not publisher.matching
    other = server.subscribe("arpz/f/robot/w$*/sensor/*", lambda k, p, att: None)
    assert not publisher.matching  # another partition's subscriber does not count
    mine = server.subscribe("arpz/f/robot/e$*/sensor/*", lambda k, p, att: None)
    assert publisher.matching
    mine.undeclare()
    other.undeclare()
    assert not publisher.matching
    robot.close()
    server.close()


def test_reopen_tells_watchers_again_which_tokens_are_alive() -> None:
    bus = MemoryBus()
    robot, ceddp = MemoryTransport(bus), MemoryTransport(bus)
    seen: list[tuple[str, bool]] = []
    ceddp.declare_token("p/ceddp")
    robot.watch_liveliness("p/*", lambda key, alive: seen.append((key, alive)))
    delivered = robot.delivered
    robot.reopen()
    assert seen == [("p/ceddp", True), ("p/ceddp", True)]
    assert robot.reopens == 1 and robot.delivered == delivered + 1
    robot.close()
    with pytest.raises(TransportError):
        robot.reopen()
