"""The reliable channel over a lossy UDP link: writer -> netem proxy -> router -> reader (TCP)."""

from __future__ import annotations

import threading
import time

import pytest

from arpz.channel import (
    QOS_RELIABLE_ALL,
    DataInfo,
    MessageLostStatus,
    QosProfile,
    Reader,
    ReaderEventCallbacks,
    Writer,
)
from tests.integration.lossy_link import lossy_link
from tests.support import wait_until

pytestmark = pytest.mark.integration


class Sink:
    def __init__(self) -> None:
        self.seqs: list[int] = []
        self.lock = threading.Lock()

    def __call__(self, payload: bytes, info: DataInfo) -> None:
        assert payload == b"%d" % info.seq
        with self.lock:
            self.seqs.append(info.seq)


@pytest.mark.parametrize("loss_pct", [10, 30])
def test_keep_all_delivers_everything_in_order_over_a_lossy_link(loss_pct: int) -> None:
    sink = Sink()
    n = 1500
    with (
        lossy_link("--loss", str(loss_pct), "--seed", "11") as link,
        Reader(link.reader_side, "arpz/f/robot/*/sensor/*", QOS_RELIABLE_ALL, sink) as reader,
        Writer(link.writer_side, "arpz/f/robot/r1/sensor/lidar", QOS_RELIABLE_ALL) as writer,
    ):
        wait_until(
            lambda: writer.matched_count == 1 and writer.wait_for_acknowledgments(0.01),
            what="match",
        )
        time.sleep(max(0.0, link.lossy_from - time.monotonic()))
        t0 = time.monotonic()
        for i in range(n):  # 1 kHz
            writer.write(b"%d" % (i + 1))
            time.sleep(max(0.0, t0 + (i + 1) / 1000 - time.monotonic()))
        wait_until(lambda: len(sink.seqs) == n, timeout_s=30, what=f"{n} samples")
        assert sink.seqs == list(range(1, n + 1))
        stats = reader.stats()
        assert stats.lost == 0 and stats.retransmitted > n * loss_pct / 100 * 0.4
        report = link.netem.stop()
    # the emulator dropped about loss_pct of the datagrams that crossed it (Zenoh packs
    # several messages into one datagram on a busy link: 623 for 1 500 samples once, so the
    # drops are measured against what crossed, not against the samples)
    assert report is not None
    crossed = report["up"]["received"]
    assert crossed > 300 and report["up"]["dropped_loss"] > crossed * loss_pct / 100 * 0.5


def test_keep_last_depth_1_at_a_high_rate_loses_and_reports_every_loss_exactly() -> None:
    sink = Sink()
    lost_events: list[MessageLostStatus] = []
    qos = QosProfile(depth=1)
    with (
        lossy_link("--loss", "30", "--seed", "11") as link,
        Reader(
            link.reader_side,
            "t/x",
            qos,
            sink,
            events=ReaderEventCallbacks(message_lost=lost_events.append),
        ) as reader,
        Writer(link.writer_side, "t/x", qos) as writer,
    ):
        wait_until(
            lambda: writer.matched_count == 1 and writer.wait_for_acknowledgments(0.01),
            what="match",
        )
        time.sleep(max(0.0, link.lossy_from - time.monotonic()))
        n = 5000
        for i in range(n):  # as fast as possible
            writer.write(b"%d" % (i + 1))

        def settled() -> bool:
            s = reader.stats()
            return s.delivered + s.lost >= n

        wait_until(settled, timeout_s=20, what="every sample delivered or reported lost")
        time.sleep(0.3)  # nothing more may arrive
        stats = reader.stats()
        assert sink.seqs == sorted(set(sink.seqs))
        assert stats.delivered + stats.lost == n
        assert stats.delivered == len(sink.seqs)
        assert stats.lost > 0 and sum(e.total_count_change for e in lost_events) == stats.lost
        assert writer.stats().overwritten_unacked >= stats.lost  # the writer saw them go
