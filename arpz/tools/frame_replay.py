"""Replay of camera frames and point clouds from a recording made by ``arpz record``.

A robot without its camera (or a bench test) can send the very frames a fleet recorded: the
driver reads one ``sensor_msgs/msg/Image`` (or ``PointCloud2``) channel of an MCAP file and
returns, at time t, the last frame recorded at or before t after the channel's first frame (a
sample-and-hold, as ``ReplayDriver`` does for scalar traces); after the last frame it holds it,
or starts again with ``loop = true``. In robot.toml::

    [[sensors]]
    name = "front"
    kind = "camera"
    rate_hz = 10
    driver = "arpz.tools.frame_replay:CameraReplay"
    options = { recording = "fleet.mcap", topic = "/robot1/front", loop = true }

``topic`` may be left out when the file has one channel of the kind. Reading MCAP needs the
``mcap`` and ``rosbags`` libraries of the server extra, which a robot install does not have:
they are imported only when this driver starts, and their absence is an error that says so.
The driver lives with the tools, not in ``arpz.robot.sensors``, because ``arpz.robot`` never
imports the server extra's libraries nor ``arpz.core.rosmsg`` (pyproject's import contracts); the
robot loads it by its path, as any user driver.
"""

from __future__ import annotations

import bisect
import struct
from pathlib import Path
from typing import Any, ClassVar

from arpz.robot.sensors.base import SensorDriver
from arpz.robot.sensors.replay import TraceError

#: what to install when the libraries are missing
_EXTRA = "pip install 'arpz[server]' (it brings mcap and rosbags)"


def load_frames(path: Path, kind: str, topic: str | None) -> tuple[list[float], list[bytes]]:
    """(times in s from the first frame, frames) of one ``kind`` channel of an arpz recording."""
    try:
        from mcap.exceptions import McapError
        from mcap.reader import make_reader

        from arpz.core.rosmsg.convert import ConversionError, from_cdr
    except ImportError as exc:
        raise TraceError(
            f"{path}: replaying frames from MCAP needs the mcap and rosbags libraries ({exc.name} "
            f"is not installed): {_EXTRA}"
        ) from None
    times: list[float] = []
    frames: list[bytes] = []
    chosen: set[str] = set()
    first_ns = 0
    try:
        with path.open("rb") as stream:
            for _, channel, message in make_reader(stream).iter_messages(log_time_order=True):
                if channel.metadata.get("arpz_kind") != kind:
                    continue
                if topic is not None and channel.topic != topic:
                    continue
                chosen.add(channel.topic)
                if len(chosen) > 1:
                    raise TraceError(
                        f"{path}: {len(chosen)} {kind} topics ({', '.join(sorted(chosen))}): "
                        "name one in the driver's 'topic' option"
                    )
                reading = from_cdr(kind, message.data)
                first_ns = first_ns or message.log_time
                times.append((message.log_time - first_ns) / 1e9)
                frames.append(reading.value)  # type: ignore[arg-type]  # bytes for these kinds
    except TraceError:
        raise
    except OSError as exc:
        raise TraceError(f"{path}: cannot read the recording: {exc.strerror}") from None
    except (McapError, ConversionError, ValueError, struct.error) as exc:
        raise TraceError(f"{path}: not a readable arpz recording: {exc}") from None
    if not frames:
        what = f"topic {topic!r} of kind {kind}" if topic else f"{kind} topic"
        raise TraceError(f"{path}: no {what} in this recording")
    return times, frames


class _FrameReplay(SensorDriver):
    kind: ClassVar[str] = ""

    def __init__(self, options: dict[str, Any], seed: int) -> None:
        super().__init__(options, seed)
        recording = options.get("recording")
        if not isinstance(recording, str):
            raise TraceError(
                f"the {self.kind} replay driver needs options.recording = 'FILE.mcap' "
                "(a recording made by arpz record)"
            )
        topic = options.get("topic")
        self.times, self.frames = load_frames(
            Path(recording), self.kind, str(topic) if topic is not None else None
        )
        self.loop = bool(options.get("loop", False))
        #: a loop lasts the recording plus one frame period, so its last frame is shown too
        period = self.times[-1] / (len(self.times) - 1) if len(self.times) > 1 else 0.0
        self.span_s = self.times[-1] + period

    def read(self, now_s: float) -> bytes:
        t = now_s % self.span_s if self.loop and self.span_s > 0 else now_s
        index = bisect.bisect_right(self.times, t) - 1
        return self.frames[max(index, 0)]


class CameraReplay(_FrameReplay):
    """Camera frames (RGB, as ``SimCamera`` makes them) from a recording's Image channel."""

    kind = "camera"


class PointCloudReplay(_FrameReplay):
    """Point clouds (x, y, z float32) from a recording's PointCloud2 channel."""

    kind = "pointcloud"
