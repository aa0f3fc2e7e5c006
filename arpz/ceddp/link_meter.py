"""Each robot link's quality, measured from the reliable channel's own counters (issue 20).

The loss-aware depth needs the link's round trip, its datagram loss and how bursty the loss is.
Nobody types them in: the channel already counts what it takes.

- **loss**: a robot's sensor writers count the samples they sent and the samples they resent
  (``TopicCounters.sent``, ``retransmitted``, in every ``RobotStats``). Between two reports,
  p = resent / (sent + resent): the share of transmissions the link lost (a lost resend is
  resent again and counts again, as a lost datagram should).
- **round trip**: the robot's clock exchanges with the CEDDP (``RobotStats.clock.delay_ns``, the
  fastest exchange of the last few, one request/reply through the same link and router), or,
  on the robot that runs the Hello probe, its median Hello round trip when that is longer.
- **burst**: the CEDDP's sensor reader counts the ACKNACKs that asked for samples and the samples
  that arrived by resend (``ReaderStats.nacks``, ``retransmitted``); their ratio is how many
  samples one loss event took, the burst length in samples (1 for independent losses). The
  reader serves the whole fleet, so this figure is the fleet's, applied to every robot.

Pure: reports in, estimates out. A robot's estimate is renewed once it has sent
``min_samples`` samples since the last one, so a slow robot's estimate is not one sample's noise,
and the loss is smoothed over windows (each new window weighs ``LOSS_WEIGHT``).
"""

from __future__ import annotations

from dataclasses import dataclass

from arpz.core import keys
from arpz.core.messages import RobotStats

#: round trip assumed before the first clock exchange or Hello came back (loopback-ish)
DEFAULT_RTT_S = 0.005
#: weight of a new window's loss in the robot's running estimate
LOSS_WEIGHT = 0.5


@dataclass(frozen=True)
class LinkEstimate:
    """One measurement of a robot's link."""

    loss_pct: float
    rtt_s: float
    burst_samples: float
    #: samples sent, and resent, in the window this was measured on
    sent: int
    resent: int

    def describe(self) -> str:
        return (
            f"loss {self.loss_pct:.2f} % ({self.resent} resent / {self.sent} sent), "
            f"rtt {self.rtt_s * 1000:.1f} ms, burst {self.burst_samples:.1f} samples"
        )


@dataclass
class _Window:
    incarnation: str = ""
    sent: int = 0
    resent: int = 0
    base_sent: int = 0
    base_resent: int = 0


def robot_totals(stats: RobotStats) -> tuple[int, int]:
    """(samples sent, samples resent) over the robot's sensor topics since it started."""
    return (
        sum(c.sent for c in stats.topics.values()),
        sum(c.retransmitted for c in stats.topics.values()),
    )


def channel_round_trip_s(round_trips: dict[str, float], robot: str) -> float | None:
    """The robot's link round trip as the reliable channel measured it (the median over its
    writers of the NACK -> resend round trip at the CEDDP's reader), or None when no writer of
    the robot was asked to resend yet."""
    own = sorted(
        rtt
        for topic, rtt in round_trips.items()
        if (parsed := keys.parse_robot_key(topic)) is not None and parsed[0] == robot
    )
    return own[len(own) // 2] if own else None


def round_trip_s(stats: RobotStats) -> float | None:
    """The link's round trip as the robot measured it, or None before any measurement."""
    found = []
    if stats.clock is not None and stats.clock.delay_ns is not None:
        found.append(stats.clock.delay_ns / 1e9)
    if stats.hello is not None and stats.hello.rtt_ms_p50 is not None:
        found.append(stats.hello.rtt_ms_p50 / 1000)
    return max(found) if found else None


class BurstMeter:
    """Samples recovered per NACK at the CEDDP's sensor reader, over the latest interval."""

    def __init__(self) -> None:
        self._last: tuple[int, int] | None = None
        self.burst_samples = 1.0

    def observe(self, retransmitted: int, nacks: int) -> float:
        if self._last is not None:
            d_resent, d_nacks = retransmitted - self._last[0], nacks - self._last[1]
            if d_nacks > 0 and d_resent >= 0:
                self.burst_samples = max(1.0, d_resent / d_nacks)
        self._last = (retransmitted, nacks)
        return self.burst_samples


class LinkMeter:
    """Per robot: a new ``LinkEstimate`` each time it has sent ``min_samples`` more samples."""

    def __init__(self, *, min_samples: int = 200) -> None:
        self.min_samples = min_samples
        self._windows: dict[str, _Window] = {}
        #: the latest estimate per robot
        self.latest: dict[str, LinkEstimate] = {}

    def forget(self, robot: str) -> None:
        self._windows.pop(robot, None)
        self.latest.pop(robot, None)

    def observe(
        self, stats: RobotStats, burst_samples: float, channel_rtt_s: float | None = None
    ) -> LinkEstimate | None:
        """Take one report; returns the robot's new estimate when its window is full. The round
        trip is the channel's own (``channel_rtt_s``, acknowledgement round trips) when it has
        one, else the robot's clock exchange or Hello round trip."""
        sent, resent = robot_totals(stats)
        window = self._windows.get(stats.robot)
        if window is None or window.incarnation != stats.incarnation or sent < window.sent:
            # a new robot or a restarted one: its counters start again from here
            self._windows[stats.robot] = _Window(stats.incarnation, sent, resent, sent, resent)
            self.latest.pop(stats.robot, None)
            return None
        window.sent, window.resent = sent, resent
        d_sent, d_resent = sent - window.base_sent, resent - window.base_resent
        if d_sent < self.min_samples:
            return None
        window.base_sent, window.base_resent = sent, resent
        previous = self.latest.get(stats.robot)
        rtt = channel_rtt_s if channel_rtt_s is not None else round_trip_s(stats)
        if rtt is None:
            rtt = previous.rtt_s if previous is not None else DEFAULT_RTT_S
        loss_pct = 100.0 * d_resent / (d_sent + d_resent)
        if previous is not None:  # smoothed: one window of a few hundred samples is noisy
            loss_pct = (1 - LOSS_WEIGHT) * previous.loss_pct + LOSS_WEIGHT * loss_pct
        estimate = LinkEstimate(
            loss_pct=loss_pct,
            rtt_s=rtt,
            burst_samples=burst_samples if d_resent > 0 else 0.0,
            sent=d_sent,
            resent=d_resent,
        )
        self.latest[stats.robot] = estimate
        return estimate
