"""Live QoS control: re-solve the QoS problem when the fleet or its links change, assign R and D.

Pure logic: the server tells the controller which robots are alive and how many topics each uses
(eq. 1: its sensor topics plus the command topics it receives, from its ``Announce``) and passes
on every robot report; the controller returns a new ``QosAssignmentMsg`` when the answer
changed, or None. An infeasible fleet keeps the previous assignment and records the optimiser's
error (which names the bound and the smallest change that would fix it). Robots answer with
``QosAck``; refusals are kept.

Two modes (``[qos] mode``):

- ``fleet``: seed 001's problem (6), one R and D per robot (arpz.ceddp.optimiser).
- ``per_topic``: a rate and a depth for every sensor topic (arpz.ceddp.topic_optimiser), weighted
  by the topic's priority (robot config) and its measured change rate (the local cache's sends),
  each robot's samples costing 1/(1 - loss) transmissions on its measured link.

In both, the loss-aware depth ("loss_aware" and "max" policies) uses the heartbeat period and
NACK delay of the sensor profile in force, and each robot's link as measured from the channel's
counters (``arpz.ceddp.link_meter``) once measured, the configured ``link_rtt_ms`` and
``link_loss_pct`` before. A measurement changes the assignment only through hysteresis: it must
move by ``hysteresis`` of the value in force (loss by at least ``loss_step_pct`` points) in two
measurements in a row, and re-solves it causes are ``min_resolve_interval_s`` apart; the
assignment then carries the measurements in its reason (an epoch in the summary and on the
dashboard).

The closed loop also tells each robot its sensor writers' heartbeat period: on a link measured
lossy (``heartbeat_loss_pct``), ``heartbeat_rtts`` measured round trips within
[``heartbeat_min_ms``, the profile's period] (``optimiser.recovery_heartbeat_s``), since a lost
last sample waits for a heartbeat; the loss-aware depth is computed with that period. Seed 001's
problem (``fleet`` with the ``paper`` depth) is open loop and leaves the robots' own period.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import msgspec

from arpz.ceddp.link_budget import LinkBudget, fit_rates
from arpz.ceddp.link_meter import BurstMeter, LinkEstimate, LinkMeter
from arpz.ceddp.optimiser import (
    LinkQuality,
    OptimiserError,
    QosLimits,
    assign_qos,
    channel_link,
    loss_aware_depth,
    recovery_heartbeat_s,
    rmax_for_budget,
    solve_closed,
)
from arpz.ceddp.topic_optimiser import TopicDemand, TopicSolution, solve_topics_closed
from arpz.core.config import QosControlConfig, QosLimitsConfig
from arpz.core.messages import QosAck, QosAssignmentMsg, RobotQos, RobotStats, TopicInfo
from arpz.core.protocol.qos import QosProfile
from arpz.core.traffic import SENSOR_QOS

log = logging.getLogger(__name__)

#: a topic's change rate is measured over at least this long (a robot reports every 0.5 s, and
#: a rarely changing topic sends a few samples a second: shorter windows are mostly noise)
CHANGE_WINDOW_S = 3.0
#: lowest change rate a topic is credited with
_MIN_CHANGE_HZ = 0.01
#: weight of a new window's change rate in the running estimate
_CHANGE_WEIGHT = 0.5
#: link measurements kept for the summary
MAX_LINK_CHANGES = 256
#: puts a measurement in force once the re-solve it causes is decided
_Commit = Callable[[], None]
#: a measurement past the hysteresis: (what moved, e.g. "link robot1"; the reason's text; commit)
_Move = tuple[str, str, _Commit]


@dataclass
class _TopicChange:
    incarnation: str = ""
    base_sent: int = 0
    base_stamp_ns: int = 0
    smoothed_hz: float | None = None
    in_force_hz: float | None = None
    pending: int = 0


class QosController:
    def __init__(
        self, config: QosControlConfig, ceddp: str, *, channel: QosProfile | None = None
    ) -> None:
        self.config = config
        self.ceddp = ceddp
        #: the sensor profile in force: its heartbeat period and NACK delay bound recovery
        self.channel = channel or SENSOR_QOS
        self.epoch = 0
        self.current: QosAssignmentMsg | None = None
        self.history: list[QosAssignmentMsg] = []
        self.acks: dict[str, QosAck] = {}
        self.refusals: list[QosAck] = []
        self.errors: list[str] = []
        self._last_topics: dict[str, int] | None = None
        #: the fleet's rate budget (samples/s) the overload governor measured; None: no budget
        self.budget_hz: float | None = None
        #: the measured links: the latest estimate per robot, and those the assignment uses
        self.meter = LinkMeter(min_samples=config.measure_samples)
        self.bursts = BurstMeter()
        self.links_in_force: dict[str, LinkEstimate] = {}
        #: the heartbeat period told to each robot whose link was measured lossy
        self._heartbeats: dict[str, float] = {}
        self._link_pending: dict[str, int] = {}
        self._changes: dict[tuple[str, str], _TopicChange] = {}
        self._last_measured_resolve_s = -math.inf
        #: moves that came within min_resolve_interval_s of the last re-solve, by subject: they
        #: re-solve at the first report after the interval (a link window can take seconds to
        #: fill again, and would otherwise have to move twice more)
        self._deferred: dict[str, _Move] = {}
        #: every re-solve a measurement caused: (epoch, reason), for the summary
        self.measured_changes: list[tuple[int, str]] = []
        #: each robot's sensor topics (from its announcement), for the per-topic problem
        self.sensors: dict[str, list[TopicInfo]] = {}
        #: per_topic: each robot link's throughput once seen full, a budget in bytes/s
        self.link_budget = LinkBudget()

    @property
    def per_topic(self) -> bool:
        return self.config.mode == "per_topic"

    @property
    def closed_loop(self) -> bool:
        """Measurements change the assignment: per topic always (they set the costs), per
        fleet only when the depth depends on the link."""
        return self.per_topic or self.config.depth_policy != "paper"

    def limits_for(self, robot: str, rmax_cap_hz: float | None = None) -> QosLimits:
        """The robot's limits from the config, with Rmax lowered to ``rmax_cap_hz`` if given."""
        cfg = self.config
        own = cfg.robots.get(robot, QosLimitsConfig())
        rmax = cfg.rmax_hz if own.rmax_hz is None else own.rmax_hz
        if rmax_cap_hz is not None:
            rmax = min(rmax, rmax_cap_hz)
        return QosLimits(
            rmax_hz=rmax,
            rmin_hz=cfg.rmin_hz if own.rmin_hz is None else own.rmin_hz,
            dmax=cfg.dmax if own.dmax is None else own.dmax,
            dmin=cfg.dmin if own.dmin is None else own.dmin,
        )

    def link_for(self, robot: str) -> LinkQuality:
        """The robot's link as the assignment uses it: measured (in force), else configured;
        always with the channel's NACK delay and the heartbeat period the robot is told."""
        heartbeat = self.heartbeat_for(robot)
        channel = (
            self.channel
            if heartbeat is None
            else msgspec.structs.replace(self.channel, heartbeat_period_s=heartbeat)
        )
        measured = self.links_in_force.get(robot)
        if measured is None:
            return channel_link(
                channel,
                rtt_s=self.config.link_rtt_ms / 1000,
                loss_pct=self.config.link_loss_pct,
            )
        return channel_link(
            channel,
            rtt_s=measured.rtt_s,
            loss_pct=min(measured.loss_pct, 99.0),
            burst_samples=measured.burst_samples,
        )

    def _heartbeat_of(self, estimate: LinkEstimate | None, *, shortened: bool = False) -> float:
        """The heartbeat period a link estimate calls for (the profile's when None). A robot
        already ``shortened`` keeps its short period down to half of ``heartbeat_loss_pct``
        (a Schmitt trigger): a few hundred samples at 1 % loss measure anywhere from 0 to 2 %,
        and a threshold crossed both ways by that noise would flip the period every window."""
        if estimate is None or not self.closed_loop:
            return self.channel.heartbeat_period_s
        cfg = self.config
        threshold = cfg.heartbeat_loss_pct / 2 if shortened else cfg.heartbeat_loss_pct
        return recovery_heartbeat_s(
            rtt_s=estimate.rtt_s,
            loss_pct=estimate.loss_pct,
            profile_s=self.channel.heartbeat_period_s,
            rtts=cfg.heartbeat_rtts,
            min_s=cfg.heartbeat_min_ms / 1000,
            loss_threshold_pct=threshold,
        )

    def heartbeat_for(self, robot: str) -> float | None:
        """The heartbeat period the robot's sensor writers are told, from its link in force;
        None (the robot's own [sensor_qos] period) on an unmeasured or lossless link and in
        the open loop."""
        return self._heartbeats.get(robot)

    # -- measurements ----------------------------------------------------------------------------

    def observe(
        self,
        stats: RobotStats,
        reader_counts: tuple[int, int] | None = None,
        channel_rtt_s: float | None = None,
    ) -> str | None:
        """Take a robot's report (and the sensor reader's (retransmitted, nacks)); returns the
        reason for a re-solve when a measurement moved past the hysteresis, else None."""
        if not self.closed_loop or stats.final:
            return None
        burst = (
            self.bursts.observe(*reader_counts)
            if reader_counts is not None
            else self.bursts.burst_samples
        )
        moves: list[_Move] = []
        estimate = self.meter.observe(stats, burst, channel_rtt_s)
        if estimate is not None:
            moves += self._link_moved(stats.robot, estimate)
        if self.per_topic:
            moves += self._changes_moved(stats)
            budget_moved = self.link_budget.observe(stats)
            if budget_moved is not None:
                moves.append((f"budget {stats.robot}", budget_moved, lambda: None))
        for move in moves:  # a newer move of the same subject replaces a deferred one
            self._deferred[move[0]] = move
        if not self._deferred:
            return None
        now = time.monotonic()
        if now - self._last_measured_resolve_s < self.config.min_resolve_interval_s:
            return None  # deferred: re-solved at the first report after the interval
        self._last_measured_resolve_s = now
        due, self._deferred = list(self._deferred.values()), {}
        for _, _, commit in due:
            commit()
        return "measured: " + "; ".join(text for _, text, _ in due)

    def _moved(self, old: float, new: float, floor: float) -> bool:
        return abs(new - old) >= max(floor, self.config.hysteresis * abs(old))

    def _link_moved(self, robot: str, estimate: LinkEstimate) -> list[_Move]:
        cfg = self.config
        old = self.links_in_force.get(robot)
        old_loss = old.loss_pct if old is not None else cfg.link_loss_pct
        old_rtt = old.rtt_s if old is not None else cfg.link_rtt_ms / 1000
        old_burst = old.burst_samples if old is not None else 0.0
        profile_hb = self.channel.heartbeat_period_s
        shortened = robot in self._heartbeats
        old_hb = self._heartbeats.get(robot, profile_hb)
        new_hb = self._heartbeat_of(estimate, shortened=shortened)
        moved = (
            self._moved(old_loss, estimate.loss_pct, cfg.loss_step_pct)
            or self._moved(old_rtt, estimate.rtt_s, 0.002)
            or self._moved(old_burst, estimate.burst_samples, 1.0)
            # the link turned lossy or clean (crossing heartbeat_loss_pct, perhaps by less than
            # loss_step_pct), or a short period moved past the hysteresis
            or (new_hb < profile_hb) != shortened
            or (shortened and self._moved(old_hb, new_hb, 0.0))
        )
        if old is None and not moved:
            self.links_in_force[robot] = estimate  # the first measurement agrees: in force
        if not moved:
            self._link_pending[robot] = 0
            self._deferred.pop(f"link {robot}", None)  # it moved back: nothing to re-solve
            return []
        self._link_pending[robot] = self._link_pending.get(robot, 0) + 1
        if self._link_pending[robot] < 2:
            return []
        before = "configured" if old is None else old.describe()

        def commit() -> None:
            self._link_pending[robot] = 0
            self.links_in_force[robot] = estimate
            if new_hb == self.channel.heartbeat_period_s:
                self._heartbeats.pop(robot, None)
            else:
                self._heartbeats[robot] = new_hb

        text = f"link {robot}: {before} -> {estimate.describe()}"
        if new_hb != old_hb:
            text += f", heartbeat {old_hb * 1000:.0f} -> {new_hb * 1000:.0f} ms"
        return [(f"link {robot}", text, commit)]

    def _changes_moved(self, stats: RobotStats) -> list[_Move]:
        """Each topic's change rate: its sends per second (the local cache sends a reading only
        when it changed, or after max_silence_s), over windows of at least CHANGE_WINDOW_S."""
        moved: list[_Move] = []
        limit = 1 + 2 * self.config.hysteresis
        for topic, counters in stats.topics.items():
            state = self._changes.setdefault((stats.robot, topic), _TopicChange())
            if state.incarnation != stats.incarnation or counters.sent < state.base_sent:
                state.incarnation, state.base_sent = stats.incarnation, counters.sent
                state.base_stamp_ns, state.smoothed_hz = stats.stamp_ns, None
                continue
            elapsed_s = (stats.stamp_ns - state.base_stamp_ns) / 1e9
            if elapsed_s < CHANGE_WINDOW_S:
                continue
            measured = max(_MIN_CHANGE_HZ, (counters.sent - state.base_sent) / elapsed_s)
            state.base_sent, state.base_stamp_ns = counters.sent, stats.stamp_ns
            # smoothed: a window holds a few Poisson-distributed sends, mostly noise
            previous = state.smoothed_hz
            new = (
                measured if previous is None else previous + _CHANGE_WEIGHT * (measured - previous)
            )
            state.smoothed_hz = new
            old = state.in_force_hz
            differs = old is None or max(new / old, old / new) >= limit
            state.pending = state.pending + 1 if differs else 0
            if not differs:  # it moved back: nothing to re-solve
                self._deferred.pop(f"{stats.robot}/{topic}", None)
            if state.pending < 2:
                continue

            def commit(state: _TopicChange = state, new: float = new) -> None:
                state.in_force_hz = new
                state.pending = 0

            was = "not measured" if old is None else f"{old:.2f} Hz"
            subject = f"{stats.robot}/{topic}"
            moved.append((subject, f"{subject} changes {was} -> {new:.2f} Hz", commit))
        return moved

    # -- solving ---------------------------------------------------------------------------------

    def set_sensors(self, robot: str, sensors: Sequence[TopicInfo]) -> None:
        self.sensors[robot] = list(sensors)

    def update(
        self, topics_per_robot: dict[str, int], reason: str, *, force: bool = False
    ) -> QosAssignmentMsg | None:
        """A new assignment if the fleet's topic counts changed (or ``force``), else None."""
        topics = {robot: count for robot, count in sorted(topics_per_robot.items()) if count > 0}
        if not topics or (topics == self._last_topics and not force):
            return None
        self._last_topics = topics
        for robot in [r for r in self.links_in_force if r not in topics]:
            del self.links_in_force[robot]
            self._heartbeats.pop(robot, None)
            self.meter.forget(robot)
        for robot in [r for r in self.sensors if r not in topics]:
            self.link_budget.forget(robot)
        cap = (
            None
            if self.budget_hz is None
            else rmax_for_budget(self.budget_hz, topics, self.config.rmin_hz)
        )
        try:
            if self.per_topic:
                robots, per_topic, t_avg = self._solve_per_topic(topics, cap)
            else:
                robots, t_avg = self._solve_fleet(topics, cap)
                per_topic = {}
        except OptimiserError as exc:
            message = f"QoS optimiser: no assignment for {topics} ({reason}): {exc}"
            self.errors.append(message)
            log.error("%s", message)
            return None
        self.epoch += 1
        self.current = QosAssignmentMsg(
            ceddp=self.ceddp,
            epoch=self.epoch,
            stamp_ns=time.time_ns(),
            reason=reason,
            t_avg=t_avg,
            topics_per_robot=topics,
            robots=robots,
            budget_hz=self.budget_hz,
            mode=self.config.mode,
            topics=per_topic,
        )
        self.history.append(self.current)
        if reason.startswith("measured: "):
            self.measured_changes.append((self.epoch, reason))
            del self.measured_changes[:-MAX_LINK_CHANGES]
        return self.current

    def _robot_qos(self, robot: str, rate_hz: float, depth: int) -> RobotQos:
        """What a robot is told: rate R, depth D, an offered deadline of ``deadline_periods``
        / R and its link's heartbeat period. Seed 001's deadline is 1/R exactly, the period the
        writer writes at, so any scheduling jitter makes a write late by its own deadline: with
        1/R the writers of a 3-robot demo counted a miss on most ticks (docs/qos-optimiser.md)."""
        return RobotQos(
            rate_hz=rate_hz,
            deadline_s=self.config.deadline_periods / rate_hz,
            depth=depth,
            heartbeat_period_s=self.heartbeat_for(robot),
        )

    def _solve_fleet(
        self, topics: dict[str, int], cap: float | None
    ) -> tuple[dict[str, RobotQos], float]:
        robots: dict[str, RobotQos] = {}
        t_avg = 0.0
        uses_link = self.config.depth_policy != "paper"
        for robot in topics:
            assignment = assign_qos(
                self.limits_for(robot, cap),
                topics,
                depth_policy=self.config.depth_policy,
                link=self.link_for(robot) if uses_link else None,
            )
            robots[robot] = self._robot_qos(robot, assignment.rate_hz, assignment.depth)
            t_avg = assignment.t_avg
        return robots, t_avg

    def _demands(self, topics: dict[str, int], limits: QosLimits) -> list[TopicDemand]:
        """Every topic of eq. 1: the sensors with their weights and costs, the received topics
        at seed 001's R (their rate is not the optimiser's to set)."""
        seed_rate = solve_closed(limits, list(topics.values())).rate_hz
        demands = []
        for robot, count in topics.items():
            loss = self.link_for(robot).loss_pct / 100
            cost = 1 / (1 - loss)
            sensors = self.sensors.get(robot, [])
            for info in sensors:
                change = self._changes.get((robot, info.topic))
                demands.append(
                    TopicDemand(
                        robot=robot,
                        topic=info.topic,
                        weight=info.priority,
                        change_hz=None if change is None else change.in_force_hz,
                        cost=cost,
                        max_rate_hz=_rate_ceiling(info),
                    )
                )
            for index in range(count - len(sensors)):
                demands.append(
                    TopicDemand(
                        robot=robot, topic=f"(received {index + 1})", fixed_hz=seed_rate, cost=cost
                    )
                )
        return demands

    def _solve_per_topic(
        self, topics: dict[str, int], cap: float | None
    ) -> tuple[dict[str, RobotQos], dict[str, dict[str, RobotQos]], float]:
        limits = self.limits_for("", cap)  # one budget for the fleet: the [qos] limits
        solution: TopicSolution = solve_topics_closed(limits, self._demands(topics, limits))
        per_topic: dict[str, dict[str, RobotQos]] = {robot: {} for robot in topics}
        for t in solution.topics:
            if not t.assigned:
                continue
            depth = t.depth
            if self.config.depth_policy != "paper":
                loss = loss_aware_depth(self.link_for(t.robot), t.rate_hz).depth
                if self.config.depth_policy == "loss_aware":
                    depth = max(limits.dmin, loss)
                else:
                    depth = max(depth, loss)
                depth = min(limits.dmax, depth)
            per_topic[t.robot][t.topic] = self._robot_qos(t.robot, t.rate_hz, depth)
        for robot, own in per_topic.items():
            self._fit_link(robot, own)
        robots = {}
        for robot, own in per_topic.items():
            if not own:  # no sensor announced yet: seed 001's share of a received topic
                fixed = [t for t in solution.topics if t.robot == robot]
                own_rates = [t.rate_hz for t in fixed]
                own_depths = [t.depth for t in fixed]
            else:
                own_rates = [q.rate_hz for q in own.values()]
                own_depths = [q.depth for q in own.values()]
            mean = sum(own_rates) / len(own_rates)
            robots[robot] = self._robot_qos(robot, mean, max(own_depths))
        return robots, per_topic, solution.t_avg

    def _fit_link(self, robot: str, own: dict[str, RobotQos]) -> None:
        """A robot whose link was seen full: its bulk topics' rates lowered to fit the budget
        (``arpz.ceddp.link_budget``), each with its deadline the same number of periods."""
        budget = self.link_budget.budget(robot)
        if budget is None:
            return
        sizes = {
            topic: size
            for topic in own
            if (size := self.link_budget.sample_bytes.get((robot, topic))) is not None
        }
        fitted = fit_rates({t: q.rate_hz for t, q in own.items()}, sizes, budget.bytes_per_s)
        for topic, rate in fitted.items():
            if rate != own[topic].rate_hz:
                own[topic] = self._robot_qos(robot, rate, own[topic].depth)

    def on_ack(self, ack: QosAck) -> str:
        """Record a robot's answer; returns a line for the event log."""
        self.acks[ack.robot] = ack
        if ack.status != "applied":
            self.refusals.append(ack)
            return f"robot {ack.robot} REFUSED QoS epoch {ack.epoch}: {ack.reason}"
        heartbeat = (
            "" if ack.heartbeat_period_s is None else f", heartbeat {ack.heartbeat_period_s:.3f} s"
        )
        return (
            f"robot {ack.robot} applied QoS epoch {ack.epoch}: "
            f"{ack.rate_hz:.2f} Hz, depth {ack.depth}{heartbeat}"
        )

    def links_summary(self) -> dict[str, object]:
        """For summary.json: each robot's measured link (latest and in force) and every
        re-solve a measurement caused."""
        return {
            "latest": {r: _link_dict(e) for r, e in self.meter.latest.items()},
            "in_force": {r: _link_dict(e) for r, e in self.links_in_force.items()},
            "heartbeat_period_s": {r: self.heartbeat_for(r) for r in self.links_in_force},
            "channel": {
                "heartbeat_period_s": self.channel.heartbeat_period_s,
                "nack_delay_s": self.channel.nack_delay_s,
            },
            "measured_changes": [{"epoch": e, "reason": r} for e, r in self.measured_changes],
            # per robot whose link was seen full: what the assignment plans on it, bytes/s
            "link_budget_bytes_per_s": {
                r: b.bytes_per_s
                for r in self.sensors
                if (b := self.link_budget.budget(r)) is not None
            },
        }


def _rate_ceiling(info: TopicInfo) -> float | None:
    """The most a sensor may be assigned: what it can be read at and what it is configured at
    (the robot never runs it faster, arpz/robot/qos.py); None: only Rmax bounds it."""
    bounds = [b for b in (info.max_rate_hz, info.configured_rate_hz) if b is not None]
    return min(bounds) if bounds else None


def _link_dict(e: LinkEstimate) -> dict[str, float]:
    return {
        "loss_pct": round(e.loss_pct, 3),
        "rtt_ms": round(e.rtt_s * 1000, 3),
        "burst_samples": round(e.burst_samples, 2),
        "sent": e.sent,
        "resent": e.resent,
    }
