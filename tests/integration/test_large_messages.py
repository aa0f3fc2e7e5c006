"""Camera frames through a real router over a lossy UDP link: FrameWriter -> netem (10 % loss
per 1500-byte frame) -> router -> FrameReader (TCP), with shared memory off on every session."""

from __future__ import annotations

import random
import threading
import time
from contextlib import ExitStack

import pytest

from arpz.reliability import QOS_FRAMES_ALL, FrameInfo, FrameReader, FrameWriter
from tests.integration.lossy_link import lossy_link
from tests.support import wait_until

pytestmark = pytest.mark.integration

NO_SHM: dict[str, object] = {"transport/shared_memory/enabled": False}
#: no datagram larger than one 1500-byte frame (docs/reliability.md, "Large samples")
ONE_FRAME: dict[str, object] = {"transport/link/tx/batch_size": 1472}
SIZE = 921_600  # 640x480 RGB


def test_camera_frames_arrive_intact_over_a_link_losing_10_percent_of_frames() -> None:
    rng = random.Random(5)
    payloads = [rng.randbytes(SIZE) for _ in range(5)]
    got: list[tuple[bytes, FrameInfo]] = []
    lock = threading.Lock()

    def on_frame(payload: bytes, info: FrameInfo) -> None:
        with lock:
            got.append((payload, info))

    with ExitStack() as stack:
        link = stack.enter_context(
            lossy_link(
                *("--loss", "10", "--per-frame", "--seed", "3"),
                every_session=NO_SHM,
                writer_session=ONE_FRAME,
            )
        )
        a, b, netem, lossy_from = link.writer_side, link.reader_side, link.netem, link.lossy_from
        reader = stack.enter_context(
            FrameReader(b, "cam/*", QOS_FRAMES_ALL, on_frame, max_frame_bytes=SIZE)
        )
        writer = stack.enter_context(
            FrameWriter(a, "cam/front", QOS_FRAMES_ALL, max_frame_bytes=SIZE)
        )
        wait_until(
            lambda: writer.matched_count == 1 and writer.wait_for_acknowledgments(0.01),
            what="match",
        )
        time.sleep(max(0.0, lossy_from - time.monotonic()))
        for p in payloads:  # 10 Hz
            writer.write(p)
            time.sleep(0.1)
        wait_until(lambda: len(got) == len(payloads), timeout_s=20, what="every frame")
        assert [p for p, _ in got] == payloads  # intact, in order
        assert [info.frame_id for _, info in got] == [1, 2, 3, 4, 5]
        assert writer.wait_for_acknowledgments(5.0)
        ws, rs = writer.stats(), reader.stats()
        assert ws.frames_sent == rs.frames.frames_delivered == 5 and ws.frames_aborted == 0
        assert rs.frames.bytes_delivered == ws.bytes_sent == 5 * SIZE
        f = rs.frames
        assert f.frames_dropped_incomplete == f.frames_dropped_over_limit == f.frames_missing == 0
        assert f.in_assembly == 0 and f.bad_fragments == 0
        assert rs.channel.delivered == ws.fragments_sent and rs.channel.lost == 0
        assert ws.channel.retransmitted > 0  # the link did lose fragments, recovered one by one
        report = netem.stop()
    assert report is not None
    up = report["up"]
    # the payload crossed the emulated link (not Zenoh's shared memory), one frame per datagram
    assert up["bytes_out"] >= 5 * SIZE
    assert up["largest_datagram"] <= 1472
    assert up["dropped_loss"] > 0.05 * up["received"]
