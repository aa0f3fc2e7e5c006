"""The per-topic QoS problem as a TOML file (``optimise --problem FILE.toml``), and its answer
as one JSON-ready document.

The file (examples/qos_problem.toml)::

    rmax_hz = 100.0        # Rmax, Rmin, Dmax, Dmin of seed 001's problem (6)
    rmin_hz = 1.0
    dmax = 5000            # optional, 5000
    dmin = 1               # optional, 1
    [[robots]]
    name = "robot1"
    [[robots.topics]]
    name = "lidar"
    weight = 2.0           # the topic's priority (optional, 1)
    change_hz = 20.0       # measured change rate (optional; unknown: changes every sample)

Unknown fields are errors, and every error names the field (``robots[0].topics[1].weight``).
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

import msgspec

from arpz.ceddp.optimiser import DEFAULT_DMAX, DEFAULT_DMIN, InvalidQosInput, QosLimits
from arpz.ceddp.topic_optimiser import TopicDemand, TopicSolution


class TopicEntry(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    name: str
    weight: float = 1.0
    change_hz: float | None = None
    #: the fastest the sensor can be read
    max_rate_hz: float | None = None
    #: transmissions per sample on the robot's link (1 + resends per sample)
    cost: float = 1.0


class RobotEntry(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    name: str
    topics: list[TopicEntry]


class TopicProblem(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    rmax_hz: float
    rmin_hz: float
    dmax: int = DEFAULT_DMAX
    dmin: int = DEFAULT_DMIN
    robots: list[RobotEntry]

    def limits(self) -> QosLimits:
        return QosLimits(rmax_hz=self.rmax_hz, rmin_hz=self.rmin_hz, dmax=self.dmax, dmin=self.dmin)

    def demands(self) -> list[TopicDemand]:
        out = []
        for r, robot in enumerate(self.robots):
            if not robot.topics:
                raise InvalidQosInput(f"robots[{r}] ({robot.name!r}) has no [[robots.topics]]")
            for t, topic in enumerate(robot.topics):
                try:
                    out.append(
                        TopicDemand(
                            robot=robot.name,
                            topic=topic.name,
                            weight=topic.weight,
                            change_hz=topic.change_hz,
                            cost=topic.cost,
                            max_rate_hz=topic.max_rate_hz,
                        )
                    )
                except InvalidQosInput as exc:
                    raise InvalidQosInput(f"robots[{r}].topics[{t}]: {exc}") from None
        return out

    def topic_counts(self) -> list[int]:
        """T_a of eq. 1 per robot: what seed 001's fleet-wide optimiser would be given."""
        return [len(robot.topics) for robot in self.robots]


def load_problem(path: Path) -> TopicProblem:
    """Read and check a problem file; InvalidQosInput names the file and the field."""
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise InvalidQosInput(f"cannot read the problem file {path}: {exc.strerror}") from None
    except tomllib.TOMLDecodeError as exc:
        raise InvalidQosInput(f"{path} is not valid TOML: {exc}") from None
    try:
        problem = msgspec.convert(data, TopicProblem)
    except msgspec.ValidationError as exc:
        where = str(exc).replace("`$.", "`").replace("`$`", "the file")
        raise InvalidQosInput(f"{path}: {where}") from None
    if not problem.robots:
        raise InvalidQosInput(f"{path}: no [[robots]]: give at least one robot with topics")
    return problem


def solution_document(solution: TopicSolution) -> dict[str, Any]:
    """The answer as the CLI prints it: one entry per topic with R and D, then the budget."""
    return {
        "topics": [
            {
                "robot": t.robot,
                "topic": t.topic,
                "R": t.rate_hz,
                "D": t.depth,
                "deadline_s": t.deadline_s,
                "weight": t.weight,
                "bound": t.bound,
            }
            for t in solution.topics
        ],
        "capacity_hz": solution.capacity_hz,
        "used_hz": solution.used_hz,
        "multiplier": solution.multiplier,
        "robots": solution.robots,
        "T_avg": solution.t_avg,
        "method": solution.method,
        "solve_time_s": solution.solve_time_s,
    }
