"""Live QoS control, hand-computed against seed 001 eq. (2)-(6).

Fleet of the paper with eq. 1 (sensor topics + the received command topic): T = 7, 6, 6, so
T_avg = 19/3 and, with Rmax 100 Hz, Rmin 1 Hz, Dmax 5000, Dmin 1:
R = 100 / (19/3) - 1 = 300/19 - 1 = 14.789 Hz; D = floor(5000 * R / 100 - 1) = floor(738.47) = 738.
A fourth robot with 6 topics: T_avg = 25/4 = 6.25, R = 16 - 1 = 15 Hz, D = floor(750 - 1) = 749.
"""

import pytest

from arpz.ceddp.qos_control import QosController
from arpz.core.config import QosControlConfig, QosLimitsConfig, SensorConfig
from arpz.core.messages import QosAck, QosAssignmentMsg, RobotQos
from arpz.robot.qos import decide

PAPER = {"robot1": 7, "robot2": 6, "robot3": 6}


def controller(**kw: object) -> QosController:
    return QosController(QosControlConfig(enabled=True, **kw), "ceddp:x")  # type: ignore[arg-type]


def test_paper_fleet_then_a_fourth_robot_then_back() -> None:
    qos = controller()
    first = qos.update(PAPER, "start")
    assert first is not None and first.epoch == 1
    assert first.t_avg == pytest.approx(19 / 3)
    for robot in PAPER:
        assert first.robots[robot].rate_hz == pytest.approx(300 / 19 - 1)
        # the offered deadline: 1.5 periods by default (deadline_periods), seed 001's 1/R is 1.0
        assert first.robots[robot].deadline_s == pytest.approx(1.5 / (300 / 19 - 1))
        assert first.robots[robot].depth == 738
    second = qos.update({**PAPER, "robot4": 6}, "robot4 joined")
    assert second is not None and second.epoch == 2
    assert second.robots["robot4"].rate_hz == pytest.approx(15.0)
    assert second.robots["robot1"].depth == 749
    third = qos.update(PAPER, "robot4 left")
    assert third is not None and third.robots == first.robots
    assert qos.update(PAPER, "nothing changed") is None
    forced = qos.update(PAPER, "requested", force=True)
    assert forced is not None and forced.epoch == 4


def test_the_paper_deadline_is_one_period_on_request() -> None:
    """deadline_periods = 1 gives seed 001's deadline 1/R exactly; below 1 is refused (a
    deadline shorter than the period would be missed on every tick)."""
    message = controller(deadline_periods=1.0).update(PAPER, "start")
    assert message is not None
    assert message.robots["robot1"].deadline_s == pytest.approx(1 / (300 / 19 - 1))
    with pytest.raises(ValueError, match="deadline_periods"):
        QosControlConfig(enabled=True, deadline_periods=0.9)


def test_per_robot_limits_from_the_config() -> None:
    qos = controller(robots={"robot2": QosLimitsConfig(rmax_hz=50.0, dmax=100)})
    message = qos.update(PAPER, "start")
    assert message is not None
    assert message.robots["robot1"].rate_hz == pytest.approx(300 / 19 - 1)
    # robot2: R = 50 / (19/3) - 1 = 150/19 - 1 = 6.8947; D = floor(100 * R / 50 - 1) = 12
    assert message.robots["robot2"].rate_hz == pytest.approx(150 / 19 - 1)
    assert message.robots["robot2"].depth == 12


def test_an_infeasible_fleet_keeps_the_previous_assignment_and_says_why() -> None:
    qos = controller(rmax_hz=10.0, rmin_hz=1.0)
    assert qos.update({"robot1": 2}, "start") is not None
    # Rmax / T_avg - Rmin = 10/7 - 1 < Rmin = 1: infeasible
    assert qos.update({"robot1": 7}, "more topics") is None
    assert qos.current is not None and qos.current.epoch == 1
    assert "Rmax" in qos.errors[-1] or "rmax" in qos.errors[-1]


def test_acks_and_refusals_are_recorded() -> None:
    qos = controller()
    applied = QosAck(
        robot="robot1",
        incarnation="i",
        ceddp="c",
        epoch=1,
        stamp_ns=1,
        status="applied",
        reason="",
        rate_hz=14.8,
        depth=738,
    )
    refused = QosAck(
        robot="robot2",
        incarnation="i",
        ceddp="c",
        epoch=1,
        stamp_ns=1,
        status="refused",
        reason="too fast",
        rate_hz=50,
        depth=0,
    )
    assert "applied" in qos.on_ack(applied)
    assert "REFUSED" in qos.on_ack(refused) and qos.refusals == [refused]


def test_a_robot_refuses_a_rate_its_sensor_cannot_deliver() -> None:
    message = QosAssignmentMsg(
        ceddp="c",
        epoch=1,
        stamp_ns=0,
        reason="",
        t_avg=6.0,
        topics_per_robot={"robot1": 6},
        robots={"robot1": RobotQos(rate_hz=20.0, deadline_s=0.05, depth=9)},
    )
    slow = [
        SensorConfig(name="temp", kind="dht11", max_rate_hz=1.0),
        SensorConfig(name="pir", kind="pir"),
    ]
    decision = decide("robot1", message, slow)
    assert not decision.applies and "temp (max 1 Hz)" in decision.reason
    assert decide("robot1", message, slow[1:]).applies
    assert not decide("robot9", message, slow[1:]).applies
