"""The downlink's "commands acknowledged" age (issue 39): a real command ``Writer`` (the
Downlink's) and a real ``Reader`` (the robot's) on the in-memory transport, the robot's downlink
cut while what it sends (its ACKNACKs) still goes through. The mission holds the fleet on this
age, as on stale readings (arpz/ceddp/mission.py)."""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import msgspec
import pytest

from arpz.ceddp.downlink import CommandAcks, Downlink
from arpz.channel import Reader
from arpz.core import keys
from arpz.core.config import CeddpConfig
from arpz.core.transport import DataCallback, Handle
from arpz.transport.memory import MemoryBus, MemoryTransport
from tests.support import wait_until

#: the planner's command rate (MissionConfig.tick_hz)
TICK_S = 0.05


class _Radio(MemoryTransport):
    """The robot's side of the link: while ``deaf``, nothing reaches its subscriptions (the
    downlink is dead: commands and heartbeats lost); what it puts (ACKNACKs) still arrives."""

    deaf = False

    def subscribe(self, key_expr: str, callback: DataCallback) -> Handle:
        def heard(key: str, payload: bytes, attachment: bytes | None) -> None:
            if not self.deaf:
                callback(key, payload, attachment)

        return super().subscribe(key_expr, heard)


class _Planner:
    """Sends a command every tick, as the mission does, and samples the age after each."""

    def __init__(self, downlink: Downlink) -> None:
        self.downlink = downlink
        self.ages: list[tuple[float, float | None]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            self.downlink.send("robot1", "velocity", b"[0.8,0.0]")
            self.ages.append(
                (time.monotonic(), self.downlink.unacknowledged_s("robot1", "velocity"))
            )
            self._stop.wait(TICK_S)

    def since(self, t0: float) -> list[float]:
        return [age for t, age in list(self.ages) if t >= t0 and age is not None]

    @property
    def last(self) -> float | None:
        return self.ages[-1][1] if self.ages else None

    def __enter__(self) -> _Planner:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(5)


@contextmanager
def _link(config: CeddpConfig) -> Iterator[tuple[Downlink, _Radio]]:
    bus = MemoryBus()
    downlink = Downlink(MemoryTransport(bus), "f", config)
    try:
        yield downlink, _Radio(bus)
    finally:
        downlink.close()


def _reader(radio: _Radio, config: CeddpConfig) -> Reader:
    qos = config.profile("command", downlink=True)
    assert qos is not None
    return Reader(radio, keys.command_key("f", "robot1", "velocity"), qos, lambda p, i: None)


def test_commands_a_robot_stops_acknowledging_age_from_the_last_acknowledged_one() -> None:
    config = CeddpConfig()
    with _link(config) as (downlink, radio):
        assert downlink.unacknowledged_s("robot1", "velocity") is None  # no writer yet
        downlink.open_robot("robot1", ["velocity"])
        with _reader(radio, config), _Planner(downlink) as planner:
            writer = downlink._outlets[("robot1", "velocity")].writer
            assert writer is not None
            wait_until(lambda: writer.matched_count == 1, what="the robot's reader matched")
            # acknowledged within the writer's 0.1 s heartbeat period while the link works
            time.sleep(1.0)  # deliberately: a second of normal running to look at
            t0 = time.monotonic()
            time.sleep(1.0)  # deliberately: the sample
            normal = planner.since(t0)
            assert len(normal) >= 10 and max(normal) < 0.3, normal

            # the downlink dies: ages grow from the last command acknowledged
            radio.deaf = True
            cut = time.monotonic()
            wait_until(
                lambda: (planner.last or 0.0) > 1.5,
                timeout_s=10,
                what="the age past 1.5 s",
            )
            held = time.monotonic() - cut
            assert writer.acknowledged_through() < writer.stats().sent
            assert planner.last == pytest.approx(held, abs=0.3)
            # it rose steadily (never reset by an overwrite)
            during = planner.since(cut + 0.3)
            assert all(b >= a for a, b in itertools.pairwise(during)), during

            # back: acknowledged again within a few heartbeat periods
            radio.deaf = False
            back = time.monotonic()
            wait_until(
                lambda: (planner.last or 1.0) < 0.2,
                timeout_s=5,
                what="the commands acknowledged again",
            )
            assert time.monotonic() - back < 1.0


def test_with_no_reader_matched_the_commands_stay_unacknowledged() -> None:
    # a robot away (its session lost: its reader unmatched, the match awaited) or gone:
    # acknowledged_through() is the last seq with nobody to acknowledge; the age says so
    config = CeddpConfig()
    with _link(config) as (downlink, radio):
        downlink.open_robot("robot1", ["velocity"])
        with _Planner(downlink) as planner:
            reader = _reader(radio, config)
            writer = downlink._outlets[("robot1", "velocity")].writer
            assert writer is not None
            wait_until(lambda: writer.matched_count == 1, what="the robot's reader matched")
            wait_until(lambda: (planner.last or 1.0) < 0.2, what="acknowledged")
            reader.close()
            gone = time.monotonic()
            wait_until(lambda: writer.matched_count == 0, what="the reader unmatched")
            wait_until(lambda: (planner.last or 0.0) > 1.0, what="the age past 1 s")
            assert writer.acknowledged_through() == writer.stats().sent  # says: all of them
            assert planner.last == pytest.approx(time.monotonic() - gone, abs=0.3)


def test_without_the_channel_the_age_is_unknown() -> None:
    plain = msgspec.structs.replace(CeddpConfig(), reliability="none")
    with _link(plain) as (downlink, _):
        downlink.open_robot("robot1", ["velocity"])
        downlink.send("robot1", "velocity", b"[0.0,0.0]")
        assert downlink.unacknowledged_s("robot1", "velocity") is None


class _Overwriting:
    """A KEEP_LAST writer whose history is full of unacknowledged commands: every write
    overwrites the oldest, and ``acknowledged_through`` follows, ``depth`` behind the last."""

    def __init__(self, depth: int) -> None:
        self.depth, self.last, self.matched_count = depth, 0, 1
        self.acked = 0

    def acknowledged_through(self) -> int:
        return max(self.acked, self.last - self.depth)


def test_overwrites_of_a_full_history_are_not_acknowledgements() -> None:
    qos = CeddpConfig().profile("command", downlink=True)
    assert qos is not None and qos.depth == 10
    acks, writer = CommandAcks(qos), _Overwriting(qos.depth)
    with acks.lock:
        for t in range(5):  # 0..4 s, one a second
            acks.written(float(t))
            writer.last += 1
    writer.acked = 3  # the robot acknowledged up to seq 3 (written at 2 s)
    assert acks.age_s(writer, 4.5) == pytest.approx(1.5)  # seq 4, written at 3 s
    for t in range(5, 40):  # the downlink is dead: 35 more, overwriting
        with acks.lock:
            acks.written(float(t))
        writer.last += 1
        assert acks.age_s(writer, t + 0.5) == pytest.approx(t - 2.5)
    writer.acked = writer.last - 2  # back: acknowledged up to two before the last
    assert acks.age_s(writer, 40.0) == pytest.approx(2.0)  # seq 39, written at 38 s
    writer.acked = writer.last
    assert acks.age_s(writer, 40.0) == 0.0
    writer.matched_count = 0  # the reader left: acknowledged_through() says "all" of what
    writer.last += 1  # follows, and nothing of it counts
    with acks.lock:
        acks.written(41.0)
    assert acks.age_s(writer, 43.0) == pytest.approx(2.0)
