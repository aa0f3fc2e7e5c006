"""A robot link's throughput as a budget for the per-topic QoS optimiser, measured from the
robot's own counters: what its sensors got through while its link was full.

Why: seed 001's problem bounds messages per second (Rmax), not bytes, so a camera's rate was
assigned as if its 921 600-byte frames cost what an IMU reading does (issue 39: a 5 Hz camera on
a 20 Mbit/s link was assigned 30.25 Hz). A robot knows when its link is full: its camera's
sending thread skips frames the link could not take (``TopicCounters.frames_skipped``). Over a
window in which frames were skipped, the bytes all its topics sent per second are what the link
carries; that, less a headroom, is the robot's budget (bytes/s). ``fit_rates`` then lowers the
rates of the robot's bulk topics (samples of ``BULK_SAMPLE_BYTES`` or more) so that what the
assignment plans fits it, small topics first: they are what a planner needs on time.

A budget is learned only from a full link, so it only ever lowers a rate. A link that got
better is found again by forgetting the budget after ``FORGET_AFTER_S`` without a skipped frame:
the next assignment offers the camera its full rate, and a link still too thin skips again
within a window. Pure: no I/O, no clock of its own (the reports' stamps).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from arpz.core.messages import RobotStats

#: a topic whose samples are this large or more is bulk: its rate is what fits the link
BULK_SAMPLE_BYTES = 16 * 1024
#: the share of the measured throughput the assignment plans to use: the rest absorbs the
#: link's variation, so its queues stay short (a full queue is latency for every topic)
HEADROOM = 0.7
#: a window is at least this long (the robot reports every 0.5 s; a frame can take seconds)
WINDOW_S = 2.0
#: a budget not confirmed by a skipped frame for this long is forgotten (the link may be better)
FORGET_AFTER_S = 60.0
#: the lowest rate a bulk topic is assigned (one frame every 20 s): it still shows the scene
MIN_BULK_HZ = 0.05
#: a new measurement moves the budget in force when it differs by this share or more
MOVE_SHARE = 0.25


@dataclass
class _Window:
    incarnation: str
    stamp_ns: int
    bytes_sent: int
    frames_skipped: int


@dataclass
class Budget:
    #: bytes per second the assignment may plan on this robot's link
    bytes_per_s: float
    #: the throughput it was measured at (bytes/s, before the headroom)
    measured_bytes_per_s: float
    #: the report stamp of the last window that confirmed it (a skipped frame), ns
    confirmed_ns: int


class LinkBudget:
    """Per robot: the budget of its link (None until its link was seen full) and the mean size
    of each topic's samples."""

    def __init__(self) -> None:
        self._windows: dict[str, _Window] = {}
        self._budgets: dict[str, Budget] = {}
        #: (robot, topic) -> mean bytes per sample sent
        self.sample_bytes: dict[tuple[str, str], float] = {}

    def budget(self, robot: str) -> Budget | None:
        return self._budgets.get(robot)

    def forget(self, robot: str) -> None:
        self._windows.pop(robot, None)
        self._budgets.pop(robot, None)

    def observe(self, stats: RobotStats) -> str | None:
        """Take a robot's report; a sentence when its budget moved (a re-solve is due)."""
        robot = stats.robot
        for topic, c in stats.topics.items():
            # per seq: a frame is counted sent when the cache passes it, given its seq (and its
            # bytes) when it is out
            if c.last_seq > 0 and c.bytes_sent > 0:
                self.sample_bytes[(robot, topic)] = c.bytes_sent / c.last_seq
        total = sum(c.bytes_sent for c in stats.topics.values())
        skipped = sum(c.frames_skipped for c in stats.topics.values())
        window = self._windows.get(robot)
        if window is None or window.incarnation != stats.incarnation or total < window.bytes_sent:
            self._windows[robot] = _Window(stats.incarnation, stats.stamp_ns, total, skipped)
            return None
        elapsed_s = (stats.stamp_ns - window.stamp_ns) / 1e9
        if elapsed_s < WINDOW_S:
            return None
        self._windows[robot] = _Window(stats.incarnation, stats.stamp_ns, total, skipped)
        old = self._budgets.get(robot)
        if skipped <= window.frames_skipped:  # the link took everything offered
            if old is not None and (stats.stamp_ns - old.confirmed_ns) / 1e9 >= FORGET_AFTER_S:
                del self._budgets[robot]
                return f"link {robot}: no frame skipped for {FORGET_AFTER_S:.0f} s, budget lifted"
            return None
        measured = (total - window.bytes_sent) / elapsed_s
        if measured <= 0:
            return None
        if old is not None and abs(measured - old.measured_bytes_per_s) < (
            MOVE_SHARE * old.measured_bytes_per_s
        ):
            old.confirmed_ns = stats.stamp_ns
            return None
        self._budgets[robot] = Budget(HEADROOM * measured, measured, stats.stamp_ns)
        return (
            f"link {robot} full at {measured * 8 / 1e6:.2f} Mbit/s (frames skipped): "
            f"budget {HEADROOM * measured * 8 / 1e6:.2f} Mbit/s"
        )


def fit_rates(
    rates_hz: Mapping[str, float], sample_bytes: Mapping[str, float], budget_bytes_per_s: float
) -> dict[str, float]:
    """The rates with the bulk topics' lowered so that sum(rate x size) fits the budget: the
    small topics keep theirs (their bytes come first), the bulk topics share what is left in
    proportion to their assigned rates' bytes, each at least ``MIN_BULK_HZ`` and never raised.
    A topic of unknown size counts as small."""
    fitted = dict(rates_hz)
    bulk = {t for t, r in rates_hz.items() if sample_bytes.get(t, 0.0) >= BULK_SAMPLE_BYTES}
    if not bulk:
        return fitted
    small = sum(r * sample_bytes.get(t, 0.0) for t, r in rates_hz.items() if t not in bulk)
    planned = sum(rates_hz[t] * sample_bytes[t] for t in bulk)
    left = max(budget_bytes_per_s - small, 0.0)
    if planned <= left:
        return fitted
    share = left / planned
    for topic in bulk:
        fitted[topic] = max(MIN_BULK_HZ, min(rates_hz[topic], rates_hz[topic] * share))
    return fitted
