"""A camera on a link slower than its frames no longer holds up the robot's other sensors
(issue 39): its frames go out on their own thread, the newest waiting, the replaced ones
skipped and counted, and the counts still reconcile."""

from __future__ import annotations

import threading
import time
from typing import Any

from arpz.core.config import SensorConfig
from arpz.core.messages import LARGE_SAMPLE_DECODER
from arpz.robot.local_cache import LocalCache
from arpz.robot.sensing import FrameSender, SensorChannel, sense
from tests.support import wait_until


class _SlowLink:
    """A FrameOutlet stand-in whose every write takes ``gate`` to open: a saturated link."""

    def __init__(self) -> None:
        self.gate = threading.Event()
        self.sent: list[bytes] = []
        self.write_failures = 0

    def send(self, payload: bytes, stamp_ns: int, *, count_unmatched: bool = False) -> bool:
        self.gate.wait(30)
        self.sent.append(payload)
        return True

    def totals(self) -> dict[str, int]:
        keys = ("write_failures", "retransmitted", "history_offered", "heartbeats", "gapped")
        totals = dict.fromkeys(keys, 0)
        totals.update(overwritten_unacked=0, deadline_missed=0)
        return totals

    def latest_undeliverable(self) -> bool:
        return False

    def unchanged(self) -> None:
        pass

    def acknowledged_through(self) -> None:
        return None

    def close(self, wait_s: float = 0.5) -> bool:
        return True


class _Frames:
    def __init__(self) -> None:
        self.n = 0

    def read(self, _now_s: float) -> bytes:
        self.n += 1
        return b"frame %d" % self.n

    def close(self) -> None:
        pass


def _camera(link: Any) -> SensorChannel:
    channel = SensorChannel(
        config=SensorConfig(name="front", kind="camera", rate_hz=5.0),
        driver=_Frames(),  # type: ignore[arg-type]
        cache=LocalCache(enabled=True),
        output=link,
        rate_hz=5.0,
    )
    channel.sender = FrameSender(channel)
    return channel


def test_a_camera_on_a_busy_link_never_blocks_the_tick_and_counts_what_it_skipped() -> None:
    link = _SlowLink()
    camera = _camera(link)
    sender = camera.sender
    assert sender is not None
    sense(camera, 0.0, "r1:i1")
    wait_until(lambda: not link.sent and sender.busy and sender._waiting is None)  # in flight
    started = time.monotonic()
    for tick in range(1, 20):  # the scheduler's ticks, while the link takes nothing
        sense(camera, tick * 0.2, "r1:i1")
    assert time.monotonic() - started < 0.5  # before: each tick waited for the link
    assert sender.skipped == 18  # 19 offered while the first was out: the newest waits
    link.gate.set()  # the link takes the one in flight and the newest waiting
    camera.stop_sending()
    frames = [LARGE_SAMPLE_DECODER.decode(p) for p in link.sent]
    assert [f.seq for f in frames] == [1, 2]  # contiguous: nothing skipped left a hole
    assert frames[1].value == b"frame 20"  # the newest
    c = camera.counters()
    assert c.produced == 20 and c.frames_skipped == 18
    assert c.produced == c.sent + c.held_back + c.write_failures
    assert c.sent == 2 == camera.seq == c.last_seq
