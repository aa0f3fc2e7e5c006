"""What ``arpz topic echo/hz/bw/delay`` do with each message: print it (``Echo``), or keep the
window's figures and print them every second (``Hz``, ``Bw``, ``Delay``), then the reader's
counters at the end. ``clock_correction`` is where ``delay`` gets the clocks' offsets."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from arpz.core.config import RobotClockConfig
from arpz.core.messages import DECODE_ERRORS
from arpz.core.transport import Transport
from arpz.robot.clock_sync import ClockSync
from arpz.tools.fleet_graph import (
    CEDDP,
    Discovery,
    TopicEntry,
    clock_offset,
)
from arpz.tools.topic_stats import (
    RateWindow,
    SizeWindow,
    ValueWindow,
    human_bytes,
)
from arpz.tools.topic_stream import Message, TopicStream, data_head
from arpz.tools.topic_text import (
    Output,
    counters_text,
    decode,
    echo_text,
    message_document,
)


class Echo:
    """``topic echo``: every message decoded, as text or one JSON object per line."""

    def __init__(self, topic: TopicEntry, out: Output, count: int) -> None:
        self.topic = topic
        self.out = out
        self.count = count
        self.printed = 0
        self.decode_errors = 0

    def on_message(self, message: Message) -> None:
        try:
            decoded = decode(self.topic, message.payload)
        except DECODE_ERRORS as exc:
            self.decode_errors += 1
            if self.decode_errors in (1, 10, 100) or self.decode_errors % 1000 == 0:
                self.out.text(f"undecodable message #{self.decode_errors} on {message.key}: {exc}")
            return
        document = message_document(self.topic, message, decoded)
        self.out.record(document)
        if self.out.text_wanted:  # with --json on stdout the JSON lines are the messages
            self.out.text(echo_text(self.topic, document))
        self.printed += 1

    @property
    def done(self) -> bool:
        return 0 < self.count <= self.printed

    def report(self, stream: TopicStream) -> None:
        """Echo prints messages, not periodic reports."""

    def final(self, stream: TopicStream) -> None:
        counters = {**stream.counters(), "decode_errors": self.decode_errors}
        self.out.record(
            {
                "final": True,
                "topic": self.topic.name,
                "messages": self.printed,
                "reader": stream.description,
                "counters": counters,
            }
        )
        self.out.text(
            f"{self.printed} messages on {self.topic.name} ({stream.description}); "
            + counters_text(counters)
        )


# ----------------------------------------------------------------------------- hz, bw, delay


class Periodic:
    """The shared loop of hz, bw and delay: figures every second, a final figure at the end."""

    what = ""

    def __init__(self, topic: TopicEntry, out: Output) -> None:
        self.topic = topic
        self.out = out
        self.start_s = time.monotonic()
        self._seen_at_report = 0
        self.messages = 0

    done = False

    def on_message(self, message: Message) -> None:
        self.messages += 1
        self.add(message)

    def add(self, message: Message) -> None:
        raise NotImplementedError

    def figures(self, now_s: float) -> dict[str, object] | None:
        raise NotImplementedError

    def figure_lines(self, figures: dict[str, object]) -> list[str]:
        raise NotImplementedError

    def report(self, stream: TopicStream) -> None:
        now = time.monotonic()
        counters = stream.counters()
        if self.messages == self._seen_at_report:
            self.out.text("no new messages")
            self.out.record(
                {
                    "t_s": round(now - self.start_s, 3),
                    "messages": self.messages,
                    "new": 0,
                    "counters": counters,
                }
            )
            return
        self._seen_at_report = self.messages
        figures = self.figures(now)
        if figures is None:
            return
        self.out.record(
            {
                "t_s": round(now - self.start_s, 3),
                "messages": self.messages,
                **figures,
                "counters": counters,
            }
        )
        for line in self.figure_lines(figures):
            self.out.text(line)
        self.out.text("\t" + counters_text(_short(counters)))

    def final(self, stream: TopicStream) -> None:
        now = time.monotonic()
        counters = stream.counters()
        figures = self.figures(now) or {}
        self.out.record(
            {
                "final": True,
                "topic": self.topic.name,
                "messages": self.messages,
                "duration_s": round(now - self.start_s, 3),
                "reader": stream.description,
                **figures,
                "counters": counters,
            }
        )
        self.out.text(
            f"{self.messages} messages on {self.topic.name} in {now - self.start_s:.1f} s "
            f"({stream.description}); {counters_text(counters)}"
        )


def _short(counters: dict[str, int]) -> dict[str, int]:
    return {k: counters[k] for k in ("lost", "retransmitted", "matched_writers") if k in counters}


def _spread_dict(spread: Any, prefix: str) -> dict[str, object]:
    return {
        f"{prefix}mean_s": spread.mean,
        f"{prefix}min_s": spread.min,
        f"{prefix}max_s": spread.max,
        f"{prefix}std_s": spread.std,
    }


class Hz(Periodic):
    def __init__(self, topic: TopicEntry, out: Output, window: int) -> None:
        super().__init__(topic, out)
        self.window = RateWindow(window)

    def add(self, message: Message) -> None:
        self.window.add(message.arrival_s)

    def figures(self, now_s: float) -> dict[str, object] | None:
        periods = self.window.periods()
        rate = self.window.rate_hz()
        if periods is None or rate is None:
            return None
        return {"rate_hz": rate, **_spread_dict(periods, "period_"), "window": periods.n + 1}

    def figure_lines(self, f: dict[str, object]) -> list[str]:
        return [
            f"average rate: {f['rate_hz']:.3f}",
            f"\tmin: {f['period_min_s']:.3f}s max: {f['period_max_s']:.3f}s "
            f"std dev: {f['period_std_s']:.5f}s window: {f['window']}",
        ]


class Bw(Periodic):
    def __init__(self, topic: TopicEntry, out: Output, window: int) -> None:
        super().__init__(topic, out)
        self.window = SizeWindow(window)

    def add(self, message: Message) -> None:
        self.window.add(message.arrival_s, len(message.payload))

    def figures(self, now_s: float) -> dict[str, object] | None:
        sizes = self.window.sizes()
        rate = self.window.bytes_per_s()
        if sizes is None or rate is None:
            return None
        return {
            "bytes_per_s": rate,
            "size_mean": sizes.mean,
            "size_min": sizes.min,
            "size_max": sizes.max,
            "window": sizes.n,
            "total_bytes": self.window.total_bytes,
        }

    def figure_lines(self, f: dict[str, object]) -> list[str]:
        return [
            f"{human_bytes(float(f['bytes_per_s']))}/s from {f['window']} messages",  # type: ignore[arg-type]
            f"\tMessage size mean: {human_bytes(float(f['size_mean']))} "  # type: ignore[arg-type]
            f"min: {human_bytes(float(f['size_min']))} "  # type: ignore[arg-type]
            f"max: {human_bytes(float(f['size_max']))}",  # type: ignore[arg-type]
        ]


#: (correction_ns or None when unknown, a sentence saying where it comes from)
Correction = tuple[int | None, str]


class Delay(Periodic):
    """Arrival (this host's wall clock) minus the source stamp, corrected by the clocks' offsets
    when they are known (``clock_correction``)."""

    def __init__(
        self,
        topic: TopicEntry,
        out: Output,
        window: int,
        correction: Callable[[], Correction],
    ) -> None:
        super().__init__(topic, out)
        self.window = ValueWindow(window)
        self._correction = correction
        self.correction_ns, self.clock_note = correction()
        self.unstamped = 0

    def add(self, message: Message) -> None:
        head = data_head(message.payload)
        stamp_ns = head[2] if head is not None else message.stamp_ns
        if stamp_ns is None:
            self.unstamped += 1
            return
        self.window.add((message.arrival_ns - stamp_ns - (self.correction_ns or 0)) / 1e9)

    def report(self, stream: TopicStream) -> None:
        self.correction_ns, self.clock_note = self._correction()
        super().report(stream)

    def figures(self, now_s: float) -> dict[str, object] | None:
        spread = self.window.spread()
        if spread is None:
            return None
        return {
            "delay_mean_s": spread.mean,
            "delay_min_s": spread.min,
            "delay_max_s": spread.max,
            "delay_std_s": spread.std,
            "window": spread.n,
            "correction_s": None if self.correction_ns is None else self.correction_ns / 1e9,
            "corrected": self.correction_ns is not None,
            "clock": self.clock_note,
            "unstamped": self.unstamped,
        }

    def figure_lines(self, f: dict[str, object]) -> list[str]:
        return [
            f"average delay: {f['delay_mean_s']:.6f}",
            f"\tmin: {f['delay_min_s']:.6f}s max: {f['delay_max_s']:.6f}s "
            f"std dev: {f['delay_std_s']:.6f}s window: {f['window']}",
            f"\t{self.clock_note}",
        ]


class HostClock:
    """This host's clock against the CEDDP's, measured as a robot measures its own (NTP-style
    exchanges on ``ceddp/clock``, the fastest of the last few: arpz.robot.clock_sync), so that a
    delay is corrected on any host, not only on the CEDDP's."""

    def __init__(self, transport: Transport, fleet: str) -> None:
        self._sync = ClockSync(RobotClockConfig(), transport, fleet)
        self._sync.first_estimate(1.0)

    def refresh(self) -> None:
        self._sync.exchange()

    def offset_ns(self) -> int | None:
        """The CEDDP's clock minus this host's, None before (or without) an answer."""
        return self._sync.stats().offset_ns


def _ms(ns: int) -> str:
    return f"{ns / 1e6:+.3f} ms"


def clock_correction(
    discovery: Discovery, topic: TopicEntry, host: HostClock | None
) -> Callable[[], Correction]:
    """What ``topic delay`` subtracts from arrival - stamp: the writer's offset to the CEDDP's
    clock (the owner robot's latest ``RobotStats.clock``; 0 for the CEDDP's own keys) minus this
    host's (measured by ``HostClock``; taken as 0 when the CEDDP does not answer). A writer
    whose offset is unknown is not corrected, and the note says so."""

    def correction() -> Correction:
        if host is not None:
            host.refresh()
        host_ns = host.offset_ns() if host is not None else None
        host_text = (
            f"this host {_ms(host_ns)}"
            if host_ns is not None
            else "this host not measured (no answer on ceddp/clock), taken as 0"
        )
        if topic.owner == CEDDP:
            writer_ns = 0
            writer_text = "writer: the CEDDP (the reference)"
        else:
            offset = clock_offset(discovery.graph().stats.get(topic.owner))
            if offset is None:
                return None, f"clock offset of {topic.owner}: offset unknown, uncorrected"
            writer_ns = offset.offset_ns
            writer_text = f"{topic.owner} {_ms(writer_ns)}"
        return (
            writer_ns - (host_ns or 0),
            f"clock offsets to the CEDDP: {writer_text}, {host_text}; corrected",
        )

    return correction
