"""The pure half of characterisation: observations in, model and eq. 10 out."""

from __future__ import annotations

import pytest

from arpz.configure.characterise import Observations, build_model, eq10
from arpz.configure.model import Computer, Model, Node, Setting, validate
from arpz.core.messages import Announce, CeddpStats, RobotStats, TopicCounters, TopicInfo, TopicRate


def _stats(robot: str, t_s: float, sent_bytes: int, cpu: float, final: bool = False):
    return RobotStats(
        robot=robot,
        incarnation="i",
        stamp_ns=int(t_s * 1e9),
        final=final,
        cpu_percent=cpu,
        topics={"imu": TopicCounters(bytes_sent=sent_bytes, rate_hz=20.0)},
    )


def test_robot_counters_are_used_when_the_ceddp_is_silent():
    obs = Observations(
        robot_stats={
            "r1": [
                _stats("r1", 0, 0, 10.0),
                _stats("r1", 2, 800, 20.0),
                _stats("r1", 3, 1000, 99.0, final=True),
            ]
        }
    )
    model = build_model(obs, wireless_bandwidth=1000)
    assert validate(model) == []
    agent = next(n for n in model.nodes if n.name == "r1_agent")
    assert agent.settings[0].cpu == pytest.approx(15.0)  # the final report is not a sample
    assert model.messages[0].bandwidth == pytest.approx(1000 / 3, abs=0.05)  # bytes/s, 1 dp
    assert model.links[0].bandwidth == 1000


def test_eq10_scales_the_running_settings_performance_by_the_frequency_ratio():
    obs = Observations(
        announce={
            "r1": Announce(
                robot="r1",
                incarnation="i",
                commands=[],
                sensors=[TopicInfo(topic="imu", kind="imu", rate_hz=20.0, value_type="float")],
            )
        },
        ceddp=[
            CeddpStats(
                stamp_ns=1,
                cpu_percent=5.0,
                topics=[TopicRate(robot="r1", topic="imu", rate_hz=15.0, bytes_per_s=10.0)],
            )
        ],
    )
    expected = Model(
        computers=[Computer(name="r1", kind="robot", capacity=100)],
        nodes=[
            Node(
                name="r1_agent",
                settings=[
                    Setting(cpu=5, performance=40),
                    Setting(cpu=9, performance=80, fixed=True),
                ],
            )
        ],
    )
    (row,) = eq10(obs, expected)
    assert (row.f_expected_hz, row.f_measured_hz, row.p_expected) == (20.0, 15.0, 80.0)
    assert row.p_measured == pytest.approx(60.0)
    (plain,) = eq10(obs)
    assert plain.p_measured == pytest.approx(75.0)


def test_eq10_counts_readings_the_local_cache_held_back():
    def report(t_s: float, held: int) -> RobotStats:
        return RobotStats(
            robot="r1",
            incarnation="i",
            stamp_ns=int(t_s * 1e9),
            final=False,
            topics={"pir": TopicCounters(held_back=held, rate_hz=1.0)},
        )

    obs = Observations(
        robot_stats={"r1": [report(0, 0), report(2, 38)]},  # 19 readings/s held back
        announce={
            "r1": Announce(
                robot="r1",
                incarnation="i",
                commands=[],
                sensors=[TopicInfo(topic="pir", kind="pir", rate_hz=20.0, value_type="str")],
            )
        },
        ceddp=[
            CeddpStats(
                stamp_ns=1,
                cpu_percent=5.0,
                topics=[TopicRate(robot="r1", topic="pir", rate_hz=1.0, bytes_per_s=10.0)],
            )
        ],
    )
    (row,) = eq10(obs)
    assert row.f_arrived_hz == pytest.approx(1.0) and row.f_held_back_hz == pytest.approx(19.0)
    assert row.p_measured == pytest.approx(100.0)
