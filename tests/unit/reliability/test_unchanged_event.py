"""A writer's assert_unchanged reaches the reader as an ``unchanged`` event (for planners that
judge freshness), and only as often as a reader checks a deadline."""

from arpz.channel import QOS_DEFAULT, Reader, ReaderEventCallbacks, UnchangedStatus, Writer
from arpz.transport.memory import MemoryBus, MemoryTransport
from tests.support import wait_until

KEY = "arpz/f/robot/r1/sensor/pir"


def test_unchanged_reaches_the_reader_with_the_topic_key() -> None:
    bus = MemoryBus()
    seen: list[UnchangedStatus] = []
    got: list[bytes] = []
    with (
        Reader(
            MemoryTransport(bus),
            "arpz/f/robot/*/sensor/*",
            QOS_DEFAULT,
            lambda payload, info: got.append(payload),
            events=ReaderEventCallbacks(unchanged=seen.append),
        ) as reader,
        Writer(MemoryTransport(bus), KEY, QOS_DEFAULT) as writer,
    ):
        wait_until(lambda: writer.matched_count == 1, what="match")
        writer.write(b"detect")
        wait_until(lambda: got == [b"detect"], what="the sample")
        for _ in range(50):  # held back 50 times in a burst: one heartbeat (rate-limited)
            writer.assert_unchanged()
        wait_until(lambda: bool(seen), what="the unchanged event")
        assert seen[0].key == KEY and seen[0].writer == writer.guid
        assert len(seen) == 1 and reader.stats().unchanged == 1
        assert writer.stats().unchanged == 50
