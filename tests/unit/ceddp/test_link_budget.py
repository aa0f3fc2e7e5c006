"""A robot link's throughput, measured when its camera skipped frames, as the per-topic
optimiser's budget (issue 39: a 5 Hz camera on a 20 Mbit/s link was assigned 30.25 Hz)."""

from __future__ import annotations

import pytest

from arpz.ceddp.link_budget import (
    FORGET_AFTER_S,
    HEADROOM,
    MIN_BULK_HZ,
    LinkBudget,
    fit_rates,
)
from arpz.ceddp.qos_control import QosController
from arpz.core.config import QosControlConfig
from arpz.core.messages import RobotStats, TopicCounters, TopicInfo

FRAME = 921_600
IMU = 40


def _stats(t_s: float, frames: int, skipped: int, imu: int) -> RobotStats:
    return RobotStats(
        robot="robot1",
        incarnation="i1",
        stamp_ns=int(t_s * 1e9),
        final=False,
        topics={
            "front": TopicCounters(
                produced=frames + skipped,
                sent=frames,
                last_seq=frames,
                bytes_sent=frames * FRAME,
                write_failures=skipped,
                frames_skipped=skipped,
            ),
            "imu": TopicCounters(produced=imu, sent=imu, last_seq=imu, bytes_sent=imu * IMU),
        },
    )


def test_a_full_link_is_measured_from_what_went_through_while_frames_were_skipped() -> None:
    meter = LinkBudget()
    assert meter.observe(_stats(0.0, 0, 0, 0)) is None
    # 2 s: 5 frames and 200 IMU readings went through, 5 frames skipped: the link was full
    moved = meter.observe(_stats(2.0, 5, 5, 200))
    assert moved is not None and "full" in moved
    budget = meter.budget("robot1")
    assert budget is not None
    measured = (5 * FRAME + 200 * IMU) / 2.0
    assert budget.measured_bytes_per_s == pytest.approx(measured)
    assert budget.bytes_per_s == pytest.approx(HEADROOM * measured)
    assert meter.sample_bytes[("robot1", "front")] == FRAME
    # the same throughput again: confirmed, nothing to re-solve
    assert meter.observe(_stats(4.0, 10, 10, 400)) is None
    # nothing skipped for FORGET_AFTER_S: the link may be better, the budget is lifted
    assert meter.observe(_stats(4.0 + FORGET_AFTER_S / 2, 15, 10, 600)) is None
    lifted = meter.observe(_stats(4.0 + FORGET_AFTER_S + 1, 20, 10, 800))
    assert lifted is not None and meter.budget("robot1") is None


def test_a_link_that_takes_everything_sets_no_budget() -> None:
    meter = LinkBudget()
    meter.observe(_stats(0.0, 0, 0, 0))
    assert meter.observe(_stats(2.0, 10, 0, 200)) is None
    assert meter.budget("robot1") is None


def test_fit_rates_lowers_only_the_bulk_topics_and_never_raises() -> None:
    sizes = {"front": float(FRAME), "imu": float(IMU)}
    budget = 2.5e6 * HEADROOM  # 20 Mbit/s
    fitted = fit_rates({"front": 5.0, "imu": 100.0}, sizes, budget)
    assert fitted["imu"] == 100.0
    assert fitted["front"] * FRAME + 100 * IMU == pytest.approx(budget)
    assert fit_rates({"front": 1.0, "imu": 100.0}, sizes, budget)["front"] == 1.0
    assert fit_rates({"front": 5.0, "imu": 100.0}, sizes, 100.0)["front"] == MIN_BULK_HZ
    assert fit_rates({"a": 5.0}, {}, 1.0) == {"a": 5.0}  # unknown size: small


def test_the_per_topic_optimiser_assigns_the_camera_what_its_link_carries() -> None:
    qos = QosController(
        QosControlConfig(enabled=True, mode="per_topic", min_resolve_interval_s=0.0), "c:1"
    )
    infos = [
        TopicInfo(topic="front", kind="camera", rate_hz=5.0, value_type="bytes"),
        TopicInfo(topic="imu", kind="imu", rate_hz=100.0, value_type="float"),
    ]
    qos.set_sensors("robot1", infos)
    first = qos.update({"robot1": 2}, "start")
    assert first is not None and first.topics["robot1"]["front"].rate_hz > 5.0  # Rmax's share
    qos.observe(_stats(0.0, 0, 0, 0))
    reason = qos.observe(_stats(2.0, 5, 5, 200))
    assert reason is not None and "link robot1 full" in reason
    again = qos.update({"robot1": 2}, reason, force=True)
    assert again is not None
    budget = qos.link_budget.budget("robot1")
    assert budget is not None
    camera = again.topics["robot1"]["front"]
    assert camera.rate_hz * FRAME <= budget.bytes_per_s
    assert camera.rate_hz == pytest.approx((budget.bytes_per_s - 100 * IMU) / FRAME, rel=0.2)
    assert camera.deadline_s == pytest.approx(qos.config.deadline_periods / camera.rate_hz)
    assert "robot1" in qos.links_summary()["link_budget_bytes_per_s"]  # type: ignore[operator]
