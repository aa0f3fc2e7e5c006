"""The topic tool's readers over the in-memory transport: what they deliver and count, and that
the default (BEST_EFFORT) reader asks nothing of the writers while --reliable does."""

from __future__ import annotations

import random
import threading
from contextlib import closing

import pytest

from arpz.channel import QOS_VIDEO, FrameWriter, HistoryFullError, Writer
from arpz.core.messages import Announce, LargeSample, Sample, encode
from arpz.core.protocol.qos import QOS_RELIABLE_ALL, QosProfile
from arpz.tools.fleet_graph import Endpoint, TopicEntry
from arpz.tools.topic_stream import (
    ChannelStream,
    FrameStream,
    Message,
    PlainStream,
    TopicStream,
    data_head,
    open_stream,
)
from arpz.transport.memory import MemoryBus, MemoryTransport
from tests.support import wait_until

KEY = "arpz/f/robot/r1/sensor/lidar"
FRAMES = "arpz/f/robot/r1/frames/front"


def entry(key: str, *, plain: bool = False, arpz_type: str = "Sample") -> TopicEntry:
    return TopicEntry(
        name="/r1/x",
        key=key,
        owner="r1",
        arpz_type=arpz_type,
        value_type=None,
        kind=None,
        ros_types=(),
        mode="none" if plain else "channel",
        announced_rate_hz=None,
        measured_rate_hz=None,
        writers=(Endpoint("r1", "", None),) if plain else (),
        readers=(),
    )


class LossyTransport(MemoryTransport):
    """Loses every ``every``-th data put of this side (control traffic goes through)."""

    def __init__(self, bus: MemoryBus, every: int) -> None:
        super().__init__(bus)
        self.every, self.n, self.lock = every, 0, threading.Lock()

    def put(
        self, key: str, payload: bytes, *, attachment: bytes | None = None, bulk: bool = False
    ) -> None:
        if key == KEY:
            with self.lock:
                self.n += 1
                if self.n % self.every == 0:
                    return
        super().put(key, payload, attachment=attachment)


def drain(stream: TopicStream, n: int) -> list[Message]:
    out: list[Message] = []
    wait_until(lambda: _take(stream, out) >= n, what=f"{n} messages")
    return out


def _take(stream: TopicStream, out: list[Message]) -> int:
    while (message := stream.get(0.0)) is not None:
        out.append(message)
    return len(out)


def sample(seq: int) -> bytes:
    return encode(Sample("r1:abc", seq, 1_000 + seq, float(seq)))


@pytest.mark.parametrize("reliable", [False, True])
def test_best_effort_counts_losses_without_resends_and_reliable_recovers_them(
    reliable: bool,
) -> None:
    bus = MemoryBus()
    n = 40
    with (
        closing(LossyTransport(bus, every=5)) as robot,
        closing(MemoryTransport(bus)) as tool,
        Writer(robot, KEY, QosProfile(depth=100, batch_max_samples=1)) as writer,
        open_stream(tool, entry(KEY), reliable=reliable) as stream,
    ):
        assert isinstance(stream, ChannelStream)
        wait_until(lambda: writer.matched_count == 1, what="match")
        for seq in range(1, n + 1):
            writer.write(sample(seq), stamp_ns=1_000 + seq)
        writer.write(sample(n + 1), stamp_ns=2_000)  # the 41st is delivered: the gap is closed
        expected = n + 1 if reliable else n + 1 - n // 5
        messages = drain(stream, expected)
        lost = 0 if reliable else n // 5
        wait_until(lambda: stream.counters()["lost"] == lost, what=f"{lost} lost")
        counters = stream.counters()
        if reliable:
            assert counters["lost"] == 0
            assert writer.stats().retransmitted >= n // 5
        else:
            assert counters["lost"] == n // 5
            assert writer.stats().retransmitted == 0  # a BEST_EFFORT reader never NACKs
        assert counters["delivered"] == len(messages) == expected
        assert counters["matched_writers"] == 1
        seqs = [data_head(m.payload)[1] for m in messages]  # type: ignore[index]
        assert seqs == sorted(seqs)
        assert all(m.writer == writer.guid and m.stamp_ns is not None for m in messages)


class MuteTransport(MemoryTransport):
    """A reader's side whose puts (ACKNACKs) never arrive: a stalled or cut-off reader."""

    def put(
        self, key: str, payload: bytes, *, attachment: bytes | None = None, bulk: bool = False
    ) -> None:
        pass


@pytest.mark.parametrize("reliable", [False, True])
def test_a_keep_all_writer_waits_only_for_a_reliable_reader(reliable: bool) -> None:
    """A KEEP_ALL writer keeps every sample until each RELIABLE reader acknowledges it: a
    RELIABLE tool that stops acknowledging fills the robot's history and its writes fail; the
    default BEST_EFFORT reader is never waited for."""
    bus = MemoryBus()
    qos = QosProfile(history=QOS_RELIABLE_ALL.history, max_samples=10, max_blocking_time_s=0.01)
    with (
        closing(MemoryTransport(bus)) as robot,
        closing(MuteTransport(bus)) as tool,
        Writer(robot, KEY, qos) as writer,
        open_stream(tool, entry(KEY), reliable=reliable),
    ):
        wait_until(lambda: writer.matched_count == 1, what="match")
        failures = 0
        for seq in range(1, 51):  # five times the history
            try:
                writer.write(sample(seq))
            except HistoryFullError:
                failures += 1
        assert (failures > 0) == reliable


def test_frames_are_reassembled_and_counted() -> None:
    bus = MemoryBus()
    frame = encode(LargeSample("r1:abc", 1, 5, bytes(range(256)) * 40))
    with (
        closing(MemoryTransport(bus)) as robot,
        closing(MemoryTransport(bus)) as tool,
        FrameWriter(robot, FRAMES, QOS_VIDEO, max_frame_bytes=2 * 2**20) as writer,
        open_stream(tool, entry(FRAMES, arpz_type="LargeSample"), reliable=False) as stream,
    ):
        assert isinstance(stream, FrameStream)
        wait_until(lambda: writer.matched_count == 1, what="match")
        writer.write(frame, stamp_ns=5)
        writer.write(frame, stamp_ns=6)
        messages = drain(stream, 2)
        assert [m.payload for m in messages] == [frame, frame]
        assert [m.frame.frame_id for m in messages if m.frame] == [1, 2]
        counters = stream.counters()
        assert counters["delivered"] == 2
        assert counters["fragments_delivered"] == 2 * messages[0].frame.fragments  # type: ignore[union-attr]
        assert counters["lost"] == counters["frames_missing"] == 0


def test_a_plain_fleet_is_read_plainly_and_gaps_in_seq_are_lost() -> None:
    bus = MemoryBus()
    with (
        closing(MemoryTransport(bus)) as robot,
        closing(MemoryTransport(bus)) as tool,
        open_stream(tool, entry(KEY, plain=True), reliable=True) as stream,
    ):
        assert isinstance(stream, PlainStream)
        for seq in (1, 2, 5, 6, 4):  # 3 and 4 missing when 5 comes; 4 then arrives late
            robot.put(KEY, sample(seq))
        messages = drain(stream, 5)
        assert len(messages) == 5
        assert stream.counters() == {
            "delivered": 5,
            "lost": 2,
            "out_of_order": 1,
            "channel_samples": 0,
            "queue_dropped": 0,
        }


def test_the_head_of_every_data_message_and_none_for_reports() -> None:
    assert data_head(sample(7)) == ("r1:abc", 7, 1_007)
    big = encode(LargeSample("r1:abc", 3, 9, random.randbytes(100_000)))
    assert data_head(big) == ("r1:abc", 3, 9)
    assert data_head(encode(Announce(robot="r1", incarnation="x", sensors=[], commands=[]))) is None
    assert data_head(b"") is None
    assert data_head(b"\x93\x01\x02") is None
