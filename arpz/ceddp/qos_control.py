"""Live QoS control: when the fleet changes, re-solve seed 001's problem (6) and assign R and D.

Pure logic: the server tells the controller which robots are alive and how many topics each uses
(eq. 1: its sensor topics plus the command topics it receives, from its ``Announce``); the
controller returns a new ``QosAssignmentMsg`` when the answer changed, or None. An infeasible
fleet keeps the previous assignment and records the optimiser's error (which names the bound and
the smallest change that would fix it). Robots answer with ``QosAck``; refusals are kept.
"""

from __future__ import annotations

import logging
import time

from arpz.ceddp.optimiser import (
    LinkQuality,
    OptimiserError,
    QosLimits,
    assign_qos,
    rmax_for_budget,
)
from arpz.config import QosControlConfig, QosLimitsConfig
from arpz.messages import QosAck, QosAssignmentMsg, RobotQos

log = logging.getLogger(__name__)


class QosController:
    def __init__(self, config: QosControlConfig, ceddp: str) -> None:
        self.config = config
        self.ceddp = ceddp
        self.epoch = 0
        self.current: QosAssignmentMsg | None = None
        self.history: list[QosAssignmentMsg] = []
        self.acks: dict[str, QosAck] = {}
        self.refusals: list[QosAck] = []
        self.errors: list[str] = []
        self._last_topics: dict[str, int] | None = None
        #: the fleet's rate budget (samples/s) the overload governor measured; None: no budget
        self.budget_hz: float | None = None

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

    def update(
        self, topics_per_robot: dict[str, int], reason: str, *, force: bool = False
    ) -> QosAssignmentMsg | None:
        """A new assignment if the fleet's topic counts changed (or ``force``), else None."""
        topics = {robot: count for robot, count in sorted(topics_per_robot.items()) if count > 0}
        if not topics or (topics == self._last_topics and not force):
            return None
        self._last_topics = topics
        link = LinkQuality(rtt_s=self.config.link_rtt_ms / 1000, loss_pct=self.config.link_loss_pct)
        robots: dict[str, RobotQos] = {}
        t_avg = 0.0
        cap = (
            None
            if self.budget_hz is None
            else rmax_for_budget(self.budget_hz, topics, self.config.rmin_hz)
        )
        try:
            for robot in topics:
                assignment = assign_qos(
                    self.limits_for(robot, cap),
                    topics,
                    depth_policy=self.config.depth_policy,
                    link=link if self.config.depth_policy != "paper" else None,
                )
                robots[robot] = RobotQos(
                    rate_hz=assignment.rate_hz,
                    deadline_s=assignment.deadline_s,
                    depth=assignment.depth,
                )
                t_avg = assignment.t_avg
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
        )
        self.history.append(self.current)
        return self.current

    def on_ack(self, ack: QosAck) -> str:
        """Record a robot's answer; returns a line for the event log."""
        self.acks[ack.robot] = ack
        if ack.status != "applied":
            self.refusals.append(ack)
            return f"robot {ack.robot} REFUSED QoS epoch {ack.epoch}: {ack.reason}"
        return (
            f"robot {ack.robot} applied QoS epoch {ack.epoch}: "
            f"{ack.rate_hz:.2f} Hz, depth {ack.depth}"
        )
