"""Bundles (arpz.core.protocol.bundle, arpz.channel.bundling): a tick's sensor messages as one
message, seen by every subscriber as the messages they carry, and unable to name another robot's
key."""

from __future__ import annotations

import time
from collections.abc import Callable

import pytest

from arpz.channel import Reader, Writer
from arpz.channel.bundling import Bundler
from arpz.core.protocol import bundle, wire
from arpz.core.protocol.qos import HistoryPolicy, QosProfile
from arpz.transport.memory import MemoryBus, MemoryTransport
from tests.support import HeldHeartbeats

ROBOT = "arpz/f/robot/r1/sensor"
QOS = QosProfile(history=HistoryPolicy.KEEP_ALL, max_samples=1, max_blocking_time_s=2.0)


def wait_until(predicate: Callable[[], bool], timeout_s: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.005)
    return predicate()


def test_entries_survive_the_round_trip_in_order() -> None:
    entries: list[bundle.Entry] = [("imu", b"a" * 30, b"h" * 26), ("lidar", b"", None)]
    payload, attachment = bundle.encode(entries)
    assert bundle.decode(payload, attachment) == entries


@pytest.mark.parametrize(
    "mangle",
    [
        lambda p, a: (p[:-1], a),  # lengths do not add up
        lambda p, a: (p, a[:-1]),  # table cut short
        lambda p, a: (p, b"\x02" + a[1:]),  # unknown version
        lambda p, a: (p, None),
        lambda p, a: (b"../x" + p[4:], a),  # a name that is not a topic
    ],
)
def test_a_malformed_bundle_is_refused(mangle: object) -> None:
    payload, attachment = bundle.encode([("imu", b"abcd", b"h"), ("gps", b"efgh", b"h")])
    bad_payload, bad_attachment = mangle(payload, attachment)  # type: ignore[operator]
    assert bundle.decode(bad_payload, bad_attachment) is None
    # the transport hands it up unopened, so the reader counts it as malformed
    key = f"{ROBOT}/_bundle"
    assert bundle.expand(key, bad_payload, bad_attachment) == [(key, bad_payload, bad_attachment)]


def test_entries_can_only_name_siblings_of_the_bundle() -> None:
    """A name is one chunk below the bundle's own parent: robot r1 cannot put on r2's keys."""
    payload, attachment = bundle.encode([("imu", b"x", None), ("gps", b"y", None)])
    keys = [k for k, _, _ in bundle.expand(f"{ROBOT}/_bundle", payload, attachment)]
    assert keys == [f"{ROBOT}/imu", f"{ROBOT}/gps"]
    assert bundle.bundle_key("arpz/f/robot/r1/sensor/imu") == f"{ROBOT}/_bundle"
    assert bundle.bundle_key("arpz/f/robot/r1/frames/cam") is None
    assert bundle.bundle_key("arpz/f/robot/r1/stats") is None


def test_one_topic_subscriptions_are_widened_and_filtered() -> None:
    assert bundle.subscription("arpz/f/robot/*/sensor/*") == ("arpz/f/robot/*/sensor/*", None)
    assert bundle.subscription("arpz/f/robot/r1/stats") == ("arpz/f/robot/r1/stats", None)
    expr, keep = bundle.subscription(f"{ROBOT}/imu")
    assert expr == f"{ROBOT}/*" and keep is not None
    assert keep(f"{ROBOT}/imu") and not keep(f"{ROBOT}/gps") and keep(f"{ROBOT}/_bundle")
    expr, keep = bundle.subscription(f"{ROBOT}/i$*")
    assert keep is not None and keep(f"{ROBOT}/imu") and not keep(f"{ROBOT}/gps")


def _fleet() -> tuple[MemoryBus, Bundler, list[str]]:
    bus = MemoryBus()
    bundler = Bundler(MemoryTransport(bus), max_bytes=1280)
    raw: list[str] = []  # what crosses the bus, before any subscriber expands it
    bus.subscribers.append(("**", lambda key, _p, _a: raw.append(key)))
    return bus, bundler, raw


def test_one_tick_leaves_as_one_message_and_arrives_as_its_messages() -> None:
    bus, bundler, raw = _fleet()
    fleet: list[tuple[str, bytes, bytes | None]] = []
    one: list[str] = []
    reader = MemoryTransport(bus)
    reader.subscribe("arpz/f/robot/*/sensor/*", lambda k, p, a: fleet.append((k, p, a)))
    reader.subscribe(f"{ROBOT}/gps", lambda k, _p, _a: one.append(k))
    pubs = {name: bundler.publisher(f"{ROBOT}/{name}") for name in ("imu", "gps", "lidar")}
    with bundler.collect():
        pubs["imu"].put(b"1", attachment=b"h1")
        pubs["gps"].put(b"2", attachment=b"h2")
        pubs["lidar"].put(b"3")
        assert raw == [], "a put inside a tick left before the tick ended"
    assert raw == [f"{ROBOT}/_bundle"]
    assert fleet == [
        (f"{ROBOT}/imu", b"1", b"h1"),
        (f"{ROBOT}/gps", b"2", b"h2"),
        (f"{ROBOT}/lidar", b"3", None),
    ]
    assert one == [f"{ROBOT}/gps"]
    assert (bundler.stats.bundles, bundler.stats.bundled) == (1, 3)


def test_outside_a_tick_and_alone_a_message_goes_on_its_own_key() -> None:
    _, bundler, raw = _fleet()
    imu = bundler.publisher(f"{ROBOT}/imu")
    imu.put(b"now")  # a writer's worker (heartbeats, resends): never held
    with bundler.collect():
        imu.put(b"alone")
    assert raw == [f"{ROBOT}/imu", f"{ROBOT}/imu"]
    assert bundler.stats.single == 1 and bundler.stats.bundles == 0


def test_a_tick_larger_than_one_bundle_is_cut_within_max_bytes() -> None:
    bus, bundler, raw = _fleet()
    got: list[bytes] = []
    MemoryTransport(bus).subscribe("arpz/f/robot/*/sensor/*", lambda _k, p, _a: got.append(p))
    pubs = [bundler.publisher(f"{ROBOT}/t{i}") for i in range(10)]
    payloads = [bytes([i]) * 400 for i in range(10)]
    with bundler.collect():
        for pub, payload in zip(pubs, payloads, strict=True):
            pub.put(payload)
    assert got == payloads
    # three 400 B entries and their overhead fill 1280 B: 3 + 3 + 3, and the last goes alone
    assert raw == [f"{ROBOT}/_bundle"] * 3 + [f"{ROBOT}/t9"]


def test_a_refused_bundle_is_counted_not_raised() -> None:
    bus = MemoryBus()
    transport = MemoryTransport(bus)
    bundler = Bundler(transport, max_bytes=1280)
    pubs = [bundler.publisher(f"{ROBOT}/t{i}") for i in range(2)]
    released: list[int] = []
    for i, pub in enumerate(pubs):
        # a writer's heartbeats announce its held seqs again: the reader NACKs the lost ones
        pub.on_released = lambda i=i: released.append(i)  # type: ignore[attr-defined]
    with bundler.collect():
        for pub in pubs:
            pub.put(b"x")
        transport.close()
    assert (bundler.stats.put_failures, bundler.stats.failed_messages) == (1, 2)
    assert sorted(released) == [0, 1]


def test_a_keep_all_writer_that_waits_for_room_sends_the_open_bundle_first() -> None:
    """A KEEP_ALL history of one is full once its sample is held in the tick's bundle: the
    writer must send what the tick holds before it waits, or it would wait for an
    acknowledgement of a sample nobody can see until its wait gave up."""
    bus = MemoryBus()
    bundler = Bundler(MemoryTransport(bus), max_bytes=1280)
    reader = Reader(MemoryTransport(bus), f"{ROBOT}/*", QOS, on_data=lambda _p, _i: None)
    writer = Writer(bundler, f"{ROBOT}/imu", QOS, block=False)
    try:
        assert wait_until(lambda: writer.matched_count == 1)
        with bundler.collect():
            writer.write(b"one")
            started = time.monotonic()
            writer.write(b"two")  # history full until "one" is acknowledged
            waited = time.monotonic() - started
        assert waited < QOS.max_blocking_time_s / 2, waited
        assert wait_until(lambda: reader.stats().delivered == 2)
        # "one" went out with the bundle, not as a resend after a heartbeat revealed it
        assert writer.stats().retransmitted == 0
    finally:
        writer.close()
        reader.close()


def test_heartbeats_never_announce_what_the_open_bundle_holds() -> None:
    """A writer's worker heartbeats while the tick that wrote holds the bundle: announcing the
    held seq made the reader NACK it and take the resend and then the bundle (a duplicate). On a
    starved robot that was 300-1 200 NACKs and as many duplicates a 25-robot run (issue 17)."""
    qos = QosProfile(heartbeat_period_s=0.005)
    bus = MemoryBus()
    bundler = Bundler(MemoryTransport(bus), max_bytes=1280)
    reader = Reader(MemoryTransport(bus), f"{ROBOT}/*", qos, on_data=lambda _p, _i: None)
    writer = Writer(bundler, f"{ROBOT}/imu", qos, block=False)
    heartbeats = HeldHeartbeats()

    watcher = MemoryTransport(bus).subscribe(wire.heartbeat_key(f"{ROBOT}/imu", "*"), heartbeats)
    try:
        assert wait_until(lambda: writer.matched_count == 1 and reader.stats().matched == 1)
        for seq in range(1, 6):
            with bundler.collect():
                heartbeats.holding = writer.write(str(seq).encode())
                time.sleep(0.04)  # the worker's heartbeat timer fires several times meanwhile
                heartbeats.holding = 0
        assert wait_until(lambda: reader.stats().delivered == 5)
        during = heartbeats.during_holds()
        assert len(during) >= 5, heartbeats.seen  # heartbeats did go out while bundles were held
        assert all(last < held for held, last in during), during
        assert heartbeats.undecodable == 0
        assert (reader.stats().nacks, reader.stats().duplicates) == (0, 0)
        assert writer.stats().retransmitted == 0
        assert wait_until(lambda: writer.acknowledged_through() == 5)
    finally:
        watcher.undeclare()
        writer.close()
        reader.close()
