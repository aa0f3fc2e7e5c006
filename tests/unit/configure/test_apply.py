"""apply without a network: eq. 10 on the paper's quantity, a solution turned into each robot's
configuration, and the robot's handler applying it to sensors and computations."""

from __future__ import annotations

from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any

import msgspec
import pytest

from arpz.configure import solve
from arpz.configure.eq10 import Eq10Node, summarise, summary_text
from arpz.configure.model import (
    Computer,
    Continuum,
    Link,
    Message,
    Model,
    Node,
    Setting,
)
from arpz.configure.plan import PlanError, eq10_nodes, plan
from arpz.configure.report import as_dict
from arpz.core.config import RobotConfig
from arpz.core.messages import ConfigurationMsg, RobotConfiguration
from arpz.robot.configuration import ConfigurationHandler, LocalObstacleCheck
from arpz.robot.scheduler import Job


def test_eq10_scales_each_node_and_compares_the_weighted_sums() -> None:
    nodes = [
        Eq10Node("a", 0.5, 100.0, 10.0, 9.0),  # 90
        Eq10Node("b", 0.25, 40.0, 20.0, 20.0),  # 40
        Eq10Node("c", 0.25, 80.0, 0.0, 0.0),  # nothing expected: keeps 80
    ]
    summary = summarise(nodes)
    assert nodes[0].p_measured == pytest.approx(90.0)
    assert nodes[2].p_measured == 80.0
    assert summary.expected == pytest.approx(50 + 10 + 20)
    assert summary.measured == pytest.approx(45 + 10 + 20)
    assert summary.deviation == pytest.approx(-5 / 80)
    assert "deviation -6.25 %" in summary_text(summary)


def test_eq10_overall_is_not_the_mean_of_node_deviations() -> None:
    """A light node far off and a heavy node on target: the paper's quantity weighs them."""
    summary = summarise([Eq10Node("heavy", 0.9, 100, 10, 10), Eq10Node("light", 0.1, 100, 10, 5)])
    mean_abs = sum(abs(n.deviation) for n in summary.nodes) / 2
    assert summary.deviation == pytest.approx(-0.05)
    assert mean_abs == pytest.approx(0.25)


def _fleet_model() -> Model:
    lidar = [
        Setting(cpu=2, performance=20, parameter=2, frequency_hz=2, bandwidth=20),
        Setting(cpu=10, performance=100, parameter=10, frequency_hz=10, bandwidth=100),
    ]
    cont = Continuum(fit="linear", parameter_fit="linear")
    return Model(
        computers=[
            Computer(name="robot1", kind="robot", capacity=6),
            Computer(name="server", kind="server", capacity=1),
        ],
        links=[Link(between=("robot1", "server"), bandwidth=1000)],
        nodes=[
            Node(
                name="lidar1",
                topic="robot1/lidar_0",
                residence=["robot1"],
                settings=lidar,
                continuum=cont,
            ),
            Node(
                name="obstacle1",
                computation="robot1/obstacle_check",
                residence=["robot1", "server"],
                settings=[Setting(cpu=1, performance=100)],
            ),
            Node(name="planner", settings=[Setting(cpu=0, performance=1)]),
        ],
        messages=[Message(source="lidar1", to="obstacle1")],
    )


def test_plan_turns_a_solution_into_each_robots_configuration() -> None:
    model = _fleet_model()
    data = as_dict(model, solve(model, problem=1, method="exact"))
    planned = plan(data)
    message = planned.message(sender="t", epoch=1, stamp_ns=0, source="test")
    assert message.robots == {
        "robot1": RobotConfiguration(
            rates_hz={"lidar_0": 6.0}, computations={"obstacle_check": "ceddp"}
        )
    }
    rows, missing = eq10_nodes(planned, {("robot1", "lidar_0"): 5.4})
    assert missing == []
    assert rows[0].p_measured == pytest.approx(60 * 5.4 / 6)
    rows, missing = eq10_nodes(planned, {})
    assert missing == ["robot1/lidar_0"] and rows[0].p_measured == 0.0


def test_plan_refuses_what_cannot_be_applied() -> None:
    model = _fleet_model()
    data = as_dict(model, solve(model, problem=1, method="greedy"))
    with pytest.raises(PlanError, match="no answer"):
        plan({**data, "objective": None})
    unmapped = {
        **data,
        "nodes": {n: {**v, "topic": None, "computation": None} for n, v in data["nodes"].items()},
    }
    with pytest.raises(PlanError, match="no node of the solution"):
        plan(unmapped)
    no_rate = {
        **data,
        "assignment": {
            **data["assignment"],
            "lidar1": {**data["assignment"]["lidar1"], "frequency_hz": None},
        },
    }
    with pytest.raises(PlanError, match="frequency_hz"):
        plan(no_rate)
    bad_topic = {
        **data,
        "nodes": {**data["nodes"], "lidar1": {**data["nodes"]["lidar1"], "topic": "lidar_0"}},
    }
    with pytest.raises(PlanError, match="robot/name"):
        plan(bad_topic)


@dataclass
class _Output:
    qos: Any = None
    retuned: list[tuple[int, float]] = field(default_factory=list)

    def retune(self, *, depth: int, deadline_s: float) -> None:
        self.retuned.append((depth, deadline_s))


def _sensor(name: str, rate_hz: float) -> Any:
    return SimpleNamespace(config=SimpleNamespace(name=name), rate_hz=rate_hz, output=_Output())


class _Computation:
    def __init__(self) -> None:
        self.here: list[bool] = []

    def run_here(self, enabled: bool) -> None:
        self.here.append(enabled)


def _handler() -> tuple[ConfigurationHandler, list[tuple[Any, Job]], _Computation, list[int]]:
    jobs = [
        (_sensor("lidar_0", 20.0), Job(0.0, 0, 0.05, lambda now: None, "lidar_0")),
        (_sensor("lidar_90", 20.0), Job(0.0, 1, 0.05, lambda now: None, "lidar_90")),
    ]
    check = _Computation()
    announced: list[int] = []
    handler = ConfigurationHandler(
        RobotConfig(robot_id="robot1", fleet="f"),
        None,  # type: ignore[arg-type]
        incarnation="i",
        sensor_jobs=jobs,
        computations={"obstacle_check": check},
        wall_ns=lambda: 7,
        on_applied=lambda: announced.append(1),
    )
    return handler, jobs, check, announced


def test_the_robot_applies_rates_and_places_and_refuses_the_rest() -> None:
    handler, jobs, check, announced = _handler()
    message = ConfigurationMsg(
        sender="s",
        epoch=3,
        stamp_ns=0,
        source="test",
        robots={
            "robot1": RobotConfiguration(
                rates_hz={"lidar_0": 6.0, "sonar": 5.0, "lidar_90": -1.0},
                computations={"obstacle_check": "robot", "mapping": "robot"},
            ),
            "robot2": RobotConfiguration(rates_hz={"lidar_0": 1.0}),
        },
    )
    ack = handler.apply(message)
    assert ack is not None
    (lidar, job), (other, other_job) = jobs
    assert lidar.rate_hz == 6.0 and job.period_s == pytest.approx(1 / 6)
    assert other.rate_hz == 20.0 and other_job.period_s == 0.05
    assert check.here == [True]
    assert ack.rates_hz == {"lidar_0": 6.0, "lidar_90": 20.0}
    assert ack.computations == {"obstacle_check": "robot"}
    assert len(ack.refused) == 3
    assert any(r.startswith("sonar:") for r in ack.refused)
    assert any(r.startswith("lidar_90: rate -1.0") for r in ack.refused)
    assert any(r.startswith("mapping:") for r in ack.refused)
    assert announced == [1] and ack.epoch == 3 and ack.stamp_ns == 7
    # a configuration for other robots only is not this robot's business
    assert handler.apply(ConfigurationMsg("s", 4, 0, "t", {"robot2": RobotConfiguration()})) is None


def test_the_local_obstacle_check_stops_inside_the_range_only() -> None:
    ranges = {"lidar_0": 2.0}
    stops: list[int] = []
    check = LocalObstacleCheck(lambda: ranges, lambda: stops.append(1), beams=["lidar_0"])
    assert not check.check()
    ranges["lidar_0"] = 0.5
    assert check.check()
    assert stops == [1] and check.stops == 1


def test_apply_refuses_bad_input_before_connecting(tmp_path: Any, capsys: Any) -> None:
    from arpz.configure.__main__ import main

    missing = main(["apply", str(tmp_path / "none.toml"), "--connect", "tcp/127.0.0.1:1"])
    assert missing == 2
    assert "arpz configure apply: error:" in capsys.readouterr().err
    # a model none of whose nodes is an arpz topic or computation: nothing to apply
    model = tmp_path / "m.json"
    model.write_text(
        '{"computers": [{"name": "r", "kind": "robot", "capacity": 100}],'
        ' "nodes": [{"name": "a", "settings": [{"cpu": 1, "performance": 1}]}]}'
    )
    assert main(["apply", str(model), "--connect", "tcp/127.0.0.1:1"]) == 2
    assert "no node of the solution" in capsys.readouterr().err


def test_undecodable_configurations_are_counted_and_the_worker_goes_on() -> None:
    handler, jobs, _check, _announced = _handler()
    handler._worker.start()  # the worker alone: no transport to open inlets on
    handler._queue.put(b"\xc1 not msgpack")
    handler._queue.put(b"\x93\x01\x02")  # msgpack, not a ConfigurationMsg
    message = ConfigurationMsg("s", 5, 0, "t", {"robot1": RobotConfiguration({"lidar_0": 4.0})})
    handler._queue.put(msgspec.msgpack.encode(message))
    handler._queue.put(None)
    handler._worker.join(timeout=5)
    assert handler.decode_errors == 2 and handler.apply_errors == 0
    assert jobs[0][0].rate_hz == 4.0  # the good one after the bad ones was applied
