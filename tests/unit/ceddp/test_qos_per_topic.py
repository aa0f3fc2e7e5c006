"""Per-topic live QoS control and its closed loop: the link measured from the channel's
counters, hysteresis, and the robot's side of a per-topic assignment. Hand-computed values in
the comments."""

from __future__ import annotations

import time

import msgspec
import pytest

from arpz.ceddp.link_meter import BurstMeter, LinkMeter, channel_round_trip_s
from arpz.ceddp.optimiser import channel_link, loss_aware_depth, recovery_heartbeat_s
from arpz.ceddp.qos_control import QosController
from arpz.core.config import QosControlConfig, SensorConfig
from arpz.core.messages import (
    ClockStats,
    QosAssignmentMsg,
    RobotQos,
    RobotStats,
    TopicCounters,
    TopicInfo,
)
from arpz.core.protocol.qos import QosProfile
from arpz.robot.qos import decide

PAPER = {"robot1": 7, "robot2": 6, "robot3": 6}


def _infos(count: int, **priorities: float) -> list[TopicInfo]:
    names = [f"s{i}" for i in range(count)]
    return [
        TopicInfo(
            topic=n, kind="lidar", rate_hz=10.0, value_type="float", priority=priorities.get(n, 1.0)
        )
        for n in names
    ]


def _assignment(robots: dict[str, RobotQos], **kw: object) -> QosAssignmentMsg:
    """An assignment of epoch 1 for ``robots`` (``kw``: mode, topics...), for the robot's side."""
    return QosAssignmentMsg(
        ceddp="c",
        epoch=1,
        stamp_ns=0,
        reason="",
        t_avg=2.0,
        topics_per_robot=dict.fromkeys(robots, 2),
        robots=robots,
        **kw,  # type: ignore[arg-type]
    )


def _controller(**kw: object) -> QosController:
    config = QosControlConfig(
        **{"enabled": True, "mode": "per_topic", "min_resolve_interval_s": 0.0, **kw}  # type: ignore[arg-type]
    )
    qos = QosController(config, "ceddp:x")
    for robot, count in PAPER.items():
        qos.set_sensors(robot, _infos(count - 1))  # one received topic each (eq. 1)
    return qos


class _Robot:
    """Cumulative counters of one robot, reported as RobotStats every ``dt_s``."""

    def __init__(self, name: str, topics: int) -> None:
        self.name, self.topics = name, topics
        self.sent = self.resent = 0
        self.stamp_ns = 0

    def report(
        self, sent: int, resent: int, *, rtt_ms: float = 1.0, dt_s: float = 0.5
    ) -> RobotStats:
        """``sent`` more samples (spread over the topics, the rest on s0), ``resent`` on s0."""
        self.sent += sent
        self.resent += resent
        self.stamp_ns += int(dt_s * 1e9)
        per = self.sent // self.topics
        counters = TopicCounters(produced=per, sent=per)
        topics = {f"s{i}": counters for i in range(self.topics)}
        topics["s0"] = msgspec.structs.replace(
            counters, sent=self.sent - per * (self.topics - 1), retransmitted=self.resent
        )
        return RobotStats(
            robot=self.name,
            incarnation="i1",
            stamp_ns=self.stamp_ns,
            final=False,
            topics=topics,
            clock=ClockStats(offset_ns=0, delay_ns=int(rtt_ms * 1e6), samples=4),
        )


# ------------------------------------------------------------------ per-topic assignment


def test_alike_topics_get_seed_001_per_topic() -> None:
    # T = 7,6,6, Rmax 100: every sensor topic R = 300/19 - 1, D = 738 (as seed 001)
    message = _controller().update(PAPER, "start")
    assert message is not None and message.mode == "per_topic"
    assert set(message.topics) == set(PAPER)
    assert len(message.topics["robot1"]) == 6  # the received topic is counted, not assigned
    for own in message.topics.values():
        for q in own.values():
            assert q.rate_hz == pytest.approx(300 / 19 - 1, rel=1e-12)
            assert q.depth == 738
    assert message.robots["robot2"].rate_hz == pytest.approx(300 / 19 - 1)


def test_priority_moves_budget_between_topics() -> None:
    # robot1's s0 priority 3: the sensors share C - 3 R* = 19 R* - 3 R* = 16 R* in weights
    # 3 + 15 x 1 = 18: s0 = 3 x 16/18 R* = 8/3 R*, every other sensor 8/9 R*
    qos = _controller()
    qos.set_sensors("robot1", _infos(6, s0=3.0))
    message = qos.update(PAPER, "start")
    assert message is not None
    seed = 300 / 19 - 1
    assert message.topics["robot1"]["s0"].rate_hz == pytest.approx(8 / 3 * seed)
    assert message.topics["robot2"]["s1"].rate_hz == pytest.approx(8 / 9 * seed)


def test_a_robot_applies_its_own_topics() -> None:
    message = _assignment(
        {"r": RobotQos(rate_hz=5.0, deadline_s=0.2, depth=9)},
        mode="per_topic",
        topics={"r": {"fast": RobotQos(rate_hz=8.0, deadline_s=0.125, depth=12)}},
    )
    sensors = [SensorConfig(name="fast", kind="lidar"), SensorConfig(name="other", kind="pir")]
    decision = decide("r", message, sensors)
    assert decision.applies
    assert decision.for_topic("fast") == RobotQos(rate_hz=8.0, deadline_s=0.125, depth=12)
    assert decision.for_topic("other") == RobotQos(rate_hz=5.0, deadline_s=0.2, depth=9)
    slow = [SensorConfig(name="fast", kind="lidar", max_rate_hz=6.0), sensors[1]]
    refused = decide("r", message, slow)
    assert not refused.applies and "fast (max 6 Hz) at 8.00 Hz" in refused.reason
    bad = msgspec.structs.replace(
        message, topics={"r": {"fast": RobotQos(rate_hz=0.0, deadline_s=1.0, depth=1)}}
    )
    assert "malformed" in decide("r", bad, sensors).reason


def test_an_assignment_never_raises_a_sensor_above_its_configured_rate() -> None:
    """Issue 39: a 5 Hz camera on a thin link was assigned 30.25 Hz. The robot runs it at its
    own 5 Hz (deadline the same number of periods), and the per-topic optimiser never offers
    it more, so the budget goes where it is used."""
    message = _assignment({"r": RobotQos(rate_hz=30.25, deadline_s=2 / 30.25, depth=9)})
    camera = SensorConfig(name="camera", kind="lidar", rate_hz=5.0)
    imu = SensorConfig(name="imu", kind="imu", rate_hz=100.0)
    decision = decide("r", message, [camera, imu])
    assert decision.applies
    own = decision.for_topic("camera")
    assert own is not None and own.rate_hz == 5.0 and own.deadline_s == pytest.approx(0.4)
    assert decision.for_topic("imu") == message.robots["r"]
    qos = _controller()
    infos = _infos(5)
    infos[0] = msgspec.structs.replace(infos[0], rate_hz=30.0, configured_rate_hz=5.0)
    qos.set_sensors("robot1", infos)
    assignment = qos.update(PAPER, "start")
    assert assignment is not None
    assert assignment.topics["robot1"]["s0"].rate_hz == pytest.approx(5.0)
    seed = 300 / 19 - 1
    assert assignment.topics["robot1"]["s1"].rate_hz > seed  # s0's share went to the others


# ------------------------------------------------------------------ the link, measured


def test_link_meter_measures_loss_rtt_and_restarts() -> None:
    meter = LinkMeter(min_samples=100)
    robot = _Robot("r", 2)
    assert meter.observe(robot.report(0, 0), 1.0) is None  # the base
    assert meter.observe(robot.report(50, 0), 1.0) is None  # not enough samples yet
    # 50 + 150 = 200 sent, 25 resent: 25 / 225 = 11.1 %
    estimate = meter.observe(robot.report(150, 25, rtt_ms=12.0), 3.0)
    assert estimate is not None
    assert estimate.loss_pct == pytest.approx(100 * 25 / 225)
    assert estimate.rtt_s == pytest.approx(0.012)
    assert estimate.burst_samples == 3.0
    restarted = msgspec.structs.replace(robot.report(0, 0), incarnation="i2")
    assert meter.observe(restarted, 1.0) is None  # counters start again


def test_the_channels_own_round_trip_is_preferred_to_the_robots_clock_exchange() -> None:
    """The acknowledgement round trip the CEDDP's sensor reader measured for a robot's writers
    (their median) is the link's RTT; the clock exchange's stands in until a writer resent."""
    round_trips = {
        "arpz/f/robot/r/sensor/a": 0.030,
        "arpz/f/robot/r/sensor/b": 0.010,
        "arpz/f/robot/r/sensor/c": 0.020,
        "arpz/f/robot/other/sensor/a": 0.500,
        "not/an/arpz/key": 0.9,
    }
    assert channel_round_trip_s(round_trips, "r") == pytest.approx(0.020)
    assert channel_round_trip_s(round_trips, "absent") is None
    meter = LinkMeter(min_samples=100)
    robot = _Robot("r", 2)
    meter.observe(robot.report(0, 0), 1.0)
    estimate = meter.observe(robot.report(200, 10, rtt_ms=12.0), 1.0, 0.020)
    assert estimate is not None and estimate.rtt_s == pytest.approx(0.020)
    estimate = meter.observe(robot.report(200, 10, rtt_ms=12.0), 1.0, None)
    assert estimate is not None and estimate.rtt_s == pytest.approx(0.012)


def test_burst_meter_is_resends_per_nack() -> None:
    bursts = BurstMeter()
    assert bursts.observe(0, 0) == 1.0
    assert bursts.observe(40, 10) == 4.0  # 40 samples recovered by 10 NACKs
    assert bursts.observe(40, 10) == 4.0  # nothing new: kept


def test_loss_aware_depth_uses_the_profile_in_force() -> None:
    # per fleet, "loss_aware", configured link 10 % and 20 ms: arpz's default sensor profile
    # (heartbeat 0.1 s, NACK 2 ms) gives ceil(R x 9 x 0.122) = ceil(16.24) = 17 at R = 14.79;
    # a profile with Fast DDS's 3 s heartbeat and 5 ms gives ceil(14.79 x 9 x 3.025) = 403
    config = QosControlConfig(
        enabled=True, depth_policy="loss_aware", link_rtt_ms=20.0, link_loss_pct=10.0
    )
    ours = QosController(config, "c").update(PAPER, "start")
    slow = QosProfile(heartbeat_period_s=3.0, nack_delay_s=0.005)
    fastdds = QosController(config, "c", channel=slow).update(PAPER, "start")
    assert ours is not None and fastdds is not None
    assert ours.robots["robot1"].depth == 17
    assert fastdds.robots["robot1"].depth == 403


def test_a_worse_link_resolves_once_with_its_measurements_and_not_again() -> None:
    qos = _controller(measure_samples=100)
    assert qos.update(PAPER, "start") is not None
    robot = _Robot("robot2", 5)
    reasons = []
    # a clean link at 4 ms: within the hysteresis of the configured 5 ms (2.5 ms), no loss
    for _ in range(3):
        reasons.append(qos.observe(robot.report(100, 0, rtt_ms=4.0)))
    assert [r for r in reasons if r] == []  # 4 ms is within 2.5 ms of 5 ms: nothing to do
    # the link turns bad: 10 % loss. One window is not enough (it must persist) ...
    assert qos.observe(robot.report(100, 11, rtt_ms=4.0)) is None
    # ... the second one re-solves, naming the measurement
    reason = qos.observe(robot.report(100, 11, rtt_ms=4.0))
    # the second window: loss (0 + 9.91)/2 = 4.95 %, then (4.95 + 9.91)/2 = 7.43 % (smoothed)
    assert reason is not None and "link robot2" in reason and "loss 7.43 %" in reason
    message = qos.update(PAPER, reason, force=True)
    assert message is not None and qos.measured_changes[-1] == (message.epoch, reason)
    # robot2's samples now cost 1/(1 - 0.0991) transmissions: its topics get less
    assert message.topics["robot2"]["s0"].rate_hz < message.topics["robot1"]["s0"].rate_hz
    # the same bad link, and small wobbles around it, change nothing more
    for resent in (11, 12, 10, 11, 13, 11):
        assert qos.observe(robot.report(100, resent, rtt_ms=4.5)) is None
    summary = qos.links_summary()
    assert summary["in_force"]["robot2"]["loss_pct"] == pytest.approx(7.43, abs=0.01)  # type: ignore[index]


def test_change_rates_weigh_topics_after_they_persist() -> None:
    # robot3's 5 sensors send 1 Hz each (the local cache holds the rest back): reports 3 s
    # apart (CHANGE_WINDOW_S) with 15 more samples; the first sets the base, two windows in a
    # row must agree before the change rates are put in force
    qos = _controller()
    assert qos.update(PAPER, "start") is not None
    robot = _Robot("robot3", 5)
    assert qos.observe(robot.report(0, 0, dt_s=3.0)) is None
    assert qos.observe(robot.report(15, 0, dt_s=3.0)) is None
    reason = qos.observe(robot.report(15, 0, dt_s=3.0))
    assert reason is not None and "robot3/s1 changes not measured -> 1.00 Hz" in reason
    message = qos.update(PAPER, reason, force=True)
    assert message is not None
    # weight sqrt(1) against sqrt(Rmax) = 10 for the topics not measured yet
    assert message.topics["robot3"]["s1"].rate_hz < message.topics["robot1"]["s1"].rate_hz / 5
    # the same rates again: nothing moves; twice as fast once: not yet (it must persist)
    assert qos.observe(robot.report(15, 0, dt_s=3.0)) is None
    assert qos.observe(robot.report(30, 0, dt_s=3.0)) is None
    assert qos.observe(robot.report(15, 0, dt_s=3.0)) is None


@pytest.mark.parametrize("priority", [0.0, -1.0, float("nan")])
def test_sensor_priority_is_validated(priority: float) -> None:
    with pytest.raises(ValueError, match="priority"):
        SensorConfig(name="x", kind="pir", priority=priority)


def test_per_topic_mode_is_a_config_choice() -> None:
    with pytest.raises(msgspec.ValidationError, match="mode"):
        msgspec.convert({"mode": "per_robot"}, QosControlConfig)
    assert msgspec.convert({"mode": "per_topic"}, QosControlConfig).mode == "per_topic"


def test_fleet_mode_with_a_loss_aware_depth_follows_the_measured_link() -> None:
    # seed 001's R = 14.79 Hz for T = 7,6,6; configured link clean: loss-aware depth 1.
    # robot2 then measures 25 / 125 = 20 % loss at 4 ms in two windows in a row: robot2's depth
    # becomes the loss-aware one at 20 %, robot1 keeps 1; the paper policy measures nothing
    config = QosControlConfig(
        enabled=True, depth_policy="loss_aware", measure_samples=100, min_resolve_interval_s=0
    )
    qos = QosController(config, "c")
    first = qos.update(PAPER, "start")
    assert first is not None and first.robots["robot2"].depth == 1
    robot = _Robot("robot2", 5)
    qos.observe(robot.report(0, 0, rtt_ms=4.0))
    assert qos.observe(robot.report(100, 25, rtt_ms=4.0)) is None  # moved once: not yet
    reason = qos.observe(robot.report(100, 25, rtt_ms=4.0))
    assert reason is not None and "link robot2: configured -> loss 20.00 %" in reason
    after = qos.update(PAPER, reason, force=True)
    assert after is not None
    assert after.robots["robot1"].depth == 1
    assert after.robots["robot2"].depth > 1
    paper = QosController(QosControlConfig(enabled=True), "c")
    assert paper.observe(_Robot("robot2", 5).report(100, 25)) is None
    assert not paper.closed_loop


# ------------------------------------------------------------------ the heartbeat of the loop


@pytest.mark.parametrize(
    ("rtt_ms", "loss_pct", "expected_s"),
    [
        (10.0, 5.0, 0.030),  # lossy: 3 round trips
        (2.0, 5.0, 0.020),  # a fast link: no shorter than heartbeat_min_ms
        (50.0, 5.0, 0.100),  # a slow link: no longer than the profile's period
        (10.0, 0.1, 0.100),  # below heartbeat_loss_pct: the profile's period
    ],
)
def test_recovery_heartbeat_is_round_trips_within_bounds(
    rtt_ms: float, loss_pct: float, expected_s: float
) -> None:
    heartbeat = recovery_heartbeat_s(
        rtt_s=rtt_ms / 1000,
        loss_pct=loss_pct,
        profile_s=0.1,
        rtts=3.0,
        min_s=0.02,
        loss_threshold_pct=0.2,
    )
    assert heartbeat == pytest.approx(expected_s)


def test_a_lossy_link_is_told_a_heartbeat_and_gets_its_own_back_when_clean() -> None:
    qos = _controller(measure_samples=100, depth_policy="loss_aware")
    start = qos.update(PAPER, "start")
    assert start is not None
    assert {q.heartbeat_period_s for q in start.robots.values()} == {None}  # not measured yet
    robot = _Robot("robot3", 5)
    qos.observe(robot.report(0, 0))
    # 1 resend per 200 sends at 6 ms: 0.50 % loss, under loss_step_pct (1 point) and a round
    # trip within the hysteresis of the configured 5 ms, yet over heartbeat_loss_pct (0.2 %):
    # the heartbeat alone moves (3 x 6 ms = 18 ms, raised to heartbeat_min_ms = 20 ms)
    assert qos.observe(robot.report(200, 1, rtt_ms=6.0)) is None  # once: not yet
    reason = qos.observe(robot.report(200, 1, rtt_ms=6.0))
    assert reason is not None and "link robot3" in reason and "heartbeat 100 -> 20 ms" in reason
    lossy = qos.update(PAPER, reason, force=True)
    assert lossy is not None
    assert lossy.robots["robot3"].heartbeat_period_s == pytest.approx(0.02)
    assert {q.heartbeat_period_s for q in lossy.topics["robot3"].values()} == {0.02}
    assert lossy.robots["robot1"].heartbeat_period_s is None  # its link was never measured lossy
    # the loss-aware depth is the one of the period the robot is told, not the profile's 0.1 s
    r = lossy.topics["robot3"]["s0"].rate_hz
    in_force = qos.links_in_force["robot3"]
    told = QosProfile(heartbeat_period_s=0.02)
    depth = loss_aware_depth(
        channel_link(told, rtt_s=in_force.rtt_s, loss_pct=in_force.loss_pct, burst_samples=1.0), r
    ).depth
    assert lossy.topics["robot3"]["s0"].depth == depth
    slow = QosProfile(heartbeat_period_s=0.1)  # what the profile's period would have given
    assert (
        depth
        < loss_aware_depth(
            channel_link(slow, rtt_s=in_force.rtt_s, loss_pct=in_force.loss_pct, burst_samples=1.0),
            r,
        ).depth
    )
    assert qos.links_summary()["heartbeat_period_s"] == {"robot3": 0.02}
    # the link heals: the smoothed loss halves each window, 0.50 -> 0.25 -> 0.12 -> 0.06 -> 0.03.
    # The short period stays down to half of heartbeat_loss_pct (0.1 %: a Schmitt trigger, so
    # that measurement noise around 0.2 % does not flip it each window), then the robot is told
    # None: its own [sensor_qos] period
    heartbeats, reasons = [], []
    for _ in range(8):
        reason = qos.observe(robot.report(200, 0, rtt_ms=6.0))
        if reason is not None:
            qos.update(PAPER, reason, force=True)
            reasons.append(reason)
        heartbeats.append(qos.heartbeat_for("robot3"))
    healed = [r for r in reasons if "heartbeat" in r]
    assert len(healed) == 1 and "heartbeat 20 -> 100 ms" in healed[0], reasons
    # two windows in a row under 0.1 % (0.06, 0.03), not the first under 0.2 % (0.12)
    assert "-> loss 0.03 %" in healed[0]
    assert heartbeats[:3] == [0.02, 0.02, 0.02] and heartbeats[-1] is None, heartbeats
    clean = qos.current
    assert clean is not None and clean.robots["robot3"].heartbeat_period_s is None


def test_a_slow_lossy_link_gets_its_period_even_within_the_hysteresis() -> None:
    """Turning lossy is a move by itself: at a 30 ms round trip the period is 2 x 30 = 60 ms,
    40 % below the profile's 100 ms, less than the hysteresis (half), yet the link is lossy."""
    slow = QosController(
        QosControlConfig(
            enabled=True,
            mode="per_topic",
            min_resolve_interval_s=0.0,
            measure_samples=100,
            link_rtt_ms=30.0,
        ),
        "c",
    )
    slow.set_sensors("robot2", _infos(4))
    slow.update({"robot2": 5}, "start")
    robot = _Robot("robot2", 5)
    slow.observe(robot.report(0, 0, rtt_ms=30.0))
    # 1 resend per 667 sends: 0.15 %, under heartbeat_loss_pct; in force (its burst moved)
    first = [slow.observe(robot.report(667, 1, rtt_ms=30.0)) for _ in range(2)]
    assert first[1] is not None and "heartbeat" not in first[1]
    assert slow.heartbeat_for("robot2") is None
    # then 1 per 100: smoothed 0.57 %, then 0.78 %. Loss moves by less than loss_step_pct, the
    # round trip and the burst not at all: only crossing heartbeat_loss_pct moves the link
    lossy = [slow.observe(robot.report(100, 1, rtt_ms=30.0)) for _ in range(2)]
    assert lossy[0] is None and lossy[1] is not None, lossy
    assert "heartbeat 100 -> 60 ms" in lossy[1]
    assert slow.heartbeat_for("robot2") == pytest.approx(0.06)


def test_the_open_loop_and_a_zero_rtts_never_assign_a_heartbeat() -> None:
    paper = QosController(QosControlConfig(enabled=True), "c")  # seed 001: fleet, paper depth
    robot = _Robot("robot2", 5)
    for _ in range(3):
        paper.observe(robot.report(200, 20, rtt_ms=10.0))
    message = paper.update(PAPER, "start")
    assert message is not None and message.robots["robot2"].heartbeat_period_s is None
    off = _controller(measure_samples=100, heartbeat_rtts=0.0)
    off.update(PAPER, "start")
    robot = _Robot("robot2", 5)
    reasons = [off.observe(robot.report(200, 20, rtt_ms=10.0)) for _ in range(4)]
    assert any(reasons)  # the loss moved: re-solved, for the rates
    message = off.update(PAPER, "measured", force=True)
    assert message is not None and message.robots["robot2"].heartbeat_period_s is None


@pytest.mark.parametrize("heartbeat", [0.0, -0.1, 1e-6, float("nan"), float("inf")])
def test_a_robot_refuses_a_malformed_heartbeat(heartbeat: float) -> None:
    qos = RobotQos(rate_hz=10.0, deadline_s=0.15, depth=5, heartbeat_period_s=heartbeat)
    decision = decide("robot1", _assignment({"robot1": qos}), [])
    assert not decision.applies and "malformed" in decision.reason


def test_heartbeat_settings_are_validated() -> None:
    with pytest.raises(ValueError, match="heartbeat_rtts"):
        QosControlConfig(heartbeat_rtts=-1.0)
    with pytest.raises(ValueError, match="heartbeat_min_ms"):
        QosControlConfig(heartbeat_min_ms=0.0)


def test_a_move_within_the_resolve_interval_resolves_at_the_first_report_after_it() -> None:
    """A link window of a slow robot takes seconds to fill: a move that came too soon after the
    last re-solve must not wait for two more windows."""
    qos = _controller(measure_samples=100, min_resolve_interval_s=0.3)
    qos.update(PAPER, "start")
    robot2, robot3 = _Robot("robot2", 5), _Robot("robot3", 5)
    for robot in (robot2, robot3):
        qos.observe(robot.report(0, 0))
    assert qos.observe(robot2.report(100, 25)) is None
    first = qos.observe(robot2.report(100, 25))
    assert first is not None and "link robot2" in first
    assert qos.observe(robot3.report(100, 25)) is None
    assert qos.observe(robot3.report(100, 25)) is None  # moved twice, but too soon: deferred
    assert qos.observe(robot3.report(10, 0)) is None  # no new window, still too soon
    time.sleep(0.35)
    later = qos.observe(robot3.report(10, 0))  # no new window either: the deferred move goes
    assert later is not None and "link robot3" in later and "link robot2" not in later
    assert qos.observe(robot3.report(10, 0)) is None  # once
