"""A solution turned into what an arpz fleet runs, and what it ran compared with what was expected.

A model meant for ``apply`` says which of its nodes are arpz things (model.py): ``topic =
"robot1/lidar_0"`` is that robot's sensor, run at the chosen setting's ``frequency_hz``;
``computation = "robot1/obstacle_check"`` is work the robot runs itself when the node is placed on
its computer, and leaves to the CEDDP when the node is placed on a server. Other nodes are the
model's only (they are solved for, not applied). Pure: a solution's JSON in (``report.as_dict``,
the same object ``solve --json`` prints), a ``ConfigurationMsg`` and eq. 10 rows out.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from arpz.configure.eq10 import Eq10Node
from arpz.core.errors import ArpzError
from arpz.core.messages import ConfigurationMsg, RobotConfiguration


class PlanError(ArpzError, ValueError):
    """A solution that cannot be applied; the message says which node and what to add."""


@dataclass(frozen=True)
class PlannedTopic:
    node: str
    robot: str
    topic: str
    rate_hz: float
    weight: float
    performance: float


@dataclass(frozen=True)
class PlannedComputation:
    node: str
    robot: str
    name: str
    #: "robot" or "ceddp"
    place: str


@dataclass(frozen=True)
class Plan:
    topics: tuple[PlannedTopic, ...]
    computations: tuple[PlannedComputation, ...]

    def message(self, *, sender: str, epoch: int, stamp_ns: int, source: str) -> ConfigurationMsg:
        robots: dict[str, RobotConfiguration] = {}
        for robot in sorted({t.robot for t in self.topics} | {c.robot for c in self.computations}):
            robots[robot] = RobotConfiguration(
                rates_hz={t.topic: t.rate_hz for t in self.topics if t.robot == robot},
                computations={c.name: c.place for c in self.computations if c.robot == robot},
            )
        return ConfigurationMsg(
            sender=sender, epoch=epoch, stamp_ns=stamp_ns, source=source, robots=robots
        )


def _split(value: str, node: str, field_name: str) -> tuple[str, str]:
    robot, sep, name = value.partition("/")
    if not sep or not robot or not name or "/" in name:
        raise PlanError(f"node {node}: {field_name} {value!r} must be 'robot/name'")
    return robot, name


def plan(solution: Mapping[str, Any]) -> Plan:
    """The fleet's part of a solution (``report.as_dict``'s object). Raises PlanError when the
    solution has no answer, maps nothing to arpz, or a topic's setting has no frequency."""
    if solution.get("objective") is None or not solution.get("assignment"):
        raise PlanError(f"the solution has no answer: {solution.get('message') or 'no placement'}")
    nodes: Mapping[str, Any] = solution.get("nodes") or {}
    topics: list[PlannedTopic] = []
    computations: list[PlannedComputation] = []
    for name, placed in solution["assignment"].items():
        info = nodes.get(name) or {}
        if info.get("topic"):
            robot, topic = _split(info["topic"], name, "topic")
            rate = placed.get("frequency_hz")
            if rate is None or rate <= 0:
                raise PlanError(
                    f"node {name} is topic {info['topic']} but its setting gives no frequency_hz: "
                    "give each of its settings a frequency_hz (the rate to run it at)"
                )
            topics.append(
                PlannedTopic(
                    name,
                    robot,
                    topic,
                    float(rate),
                    float(info.get("weight", 1.0)),
                    float(placed["performance"]),
                )
            )
        if info.get("computation"):
            robot, what = _split(info["computation"], name, "computation")
            on = info.get("on")
            if on not in ("robot", "server"):
                raise PlanError(
                    f"node {name}: the solution does not say what kind of computer "
                    f"{placed['computer']} is (nodes.{name}.on): solve the model again"
                )
            if on == "robot" and placed["computer"] != robot:
                raise PlanError(
                    f"node {name} ({info['computation']}) is placed on {placed['computer']}, "
                    f"another robot: give it residence [{robot!r}, <servers>]"
                )
            computations.append(
                PlannedComputation(name, robot, what, "robot" if on == "robot" else "ceddp")
            )
    if not topics and not computations:
        raise PlanError(
            "no node of the solution is an arpz topic or computation: give nodes a "
            "topic = 'robot/topic' or computation = 'robot/name' in the model (docs/configure.md)"
        )
    return Plan(tuple(topics), tuple(computations))


def eq10_nodes(
    planned: Plan, measured_hz: Mapping[tuple[str, str], float]
) -> tuple[list[Eq10Node], list[str]]:
    """Eq. 10 per planned topic from the measured rates ((robot, topic) -> Hz), and the topics
    that were not measured at all (reported, not silently left out of the sum)."""
    rows: list[Eq10Node] = []
    missing: list[str] = []
    for t in planned.topics:
        f = measured_hz.get((t.robot, t.topic))
        if f is None:
            missing.append(f"{t.robot}/{t.topic}")
            f = 0.0
        rows.append(Eq10Node(t.node, t.weight, t.performance, t.rate_hz, f))
    return rows, missing
