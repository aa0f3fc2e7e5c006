"""The overload governor and the budget's way into seed 001's problem, with numbers by hand."""

from __future__ import annotations

import pytest

from arpz.ceddp.cache_control import CacheControl
from arpz.ceddp.control import ControlWorker
from arpz.ceddp.downlink import Downlink
from arpz.ceddp.ingest import Ingest
from arpz.ceddp.optimiser import QosLimits, rmax_for_budget, solve
from arpz.ceddp.overload import BudgetChange, LoadSample, OverloadGovernor
from arpz.ceddp.planner import Planner
from arpz.ceddp.qos_control import QosController
from arpz.core.config import CeddpConfig, OverloadConfig, QosControlConfig
from arpz.transport.memory import MemoryBus, MemoryTransport

CONFIG = OverloadConfig(
    busy_bound=0.9,
    latency_bound_ms=100.0,
    trigger_intervals=2,
    headroom=0.8,
    hold_intervals=3,
    recover_intervals=4,
    recover_step=1.25,
)


def interval(rate_hz: float, load: float, p99_ms: float | None) -> LoadSample:
    return LoadSample(
        interval_s=0.5, processed=int(rate_hz * 0.5), load=load, latency_ms_p99=p99_ms
    )


def test_capacity_is_measured_at_any_load_as_samples_per_busy_second() -> None:
    governor = OverloadGovernor(CONFIG)
    assert governor.observe(interval(1000, 0.25, 2.0)) is None
    assert governor.capacity_hz == pytest.approx(4000)
    governor.observe(interval(1000, 0.5, 2.0))  # 2000: smoothed half and half
    assert governor.capacity_hz == pytest.approx(3000)
    # too few samples or too little load to say anything: the estimate stays
    governor.observe(LoadSample(interval_s=0.5, processed=10, load=0.5, latency_ms_p99=1.0))
    governor.observe(interval(1000, 0.01, 1.0))
    assert governor.capacity_hz == pytest.approx(3000)


def test_a_busy_ceddp_with_high_latency_cuts_the_budget_after_the_trigger_intervals() -> None:
    governor = OverloadGovernor(CONFIG)
    assert governor.observe(interval(1200, 1.0, 900.0)) is None  # one interval is not enough
    change = governor.observe(interval(1200, 1.0, 1500.0))
    assert change is not None
    assert change.budget_hz == pytest.approx(0.8 * 1200)
    assert change.reason.startswith("overload: ingest busy 100%")
    assert "1500 ms" in change.reason and "budget 960 samples/s" in change.reason
    assert governor.budget_hz == change.budget_hz
    assert governor.summary()["change_count"] == 1


@pytest.mark.parametrize(
    ("load", "p99_ms"),
    [
        (1.0, 50.0),  # saturated but keeping up: within the latency bound
        (0.5, 5000.0),  # late samples, but not the CEDDP's doing (clock offset, slow link)
        (1.0, None),  # nothing arrived
    ],
)
def test_only_a_busy_and_late_ceddp_is_overloaded(load: float, p99_ms: float | None) -> None:
    governor = OverloadGovernor(CONFIG)
    for _ in range(10):
        assert governor.observe(interval(1000, load, p99_ms)) is None
    assert governor.budget_hz is None


def test_the_governor_holds_while_the_backlog_drains_then_cuts_again_if_still_overloaded() -> None:
    governor = OverloadGovernor(CONFIG)
    governor.observe(interval(1000, 1.0, 900.0))
    first = governor.observe(interval(1000, 1.0, 900.0))
    assert first is not None and first.budget_hz == pytest.approx(800)
    for _ in range(CONFIG.hold_intervals):  # still draining at full load: no second cut
        assert governor.observe(interval(1000, 1.0, 900.0)) is None
    second = governor.observe(interval(1000, 1.0, 900.0))
    assert second is not None  # the overloaded run continued through the hold
    assert second.budget_hz == pytest.approx(640)  # never above the last budget x headroom


def test_calm_intervals_raise_the_budget_up_to_the_measured_capacity_then_lift_it() -> None:
    governor = OverloadGovernor(CONFIG)
    governor.observe(interval(1000, 1.0, 900.0))
    governor.observe(interval(1000, 1.0, 900.0))
    assert governor.budget_hz == pytest.approx(800)
    for _ in range(CONFIG.hold_intervals):
        governor.observe(interval(800, 1.0, 300.0))
    # the fleet sends its budget now and the CEDDP is calm: 800 at 40 % load, so capacity 2000
    changes = [governor.observe(interval(800, 0.4, 10.0)) for _ in range(CONFIG.recover_intervals)]
    raised = changes[-1]
    assert changes[:-1] == [None] * (CONFIG.recover_intervals - 1)
    assert raised is not None and raised.budget_hz == pytest.approx(1000)
    assert "raised to 1000" in raised.reason
    # the fleet shrank: it uses under half of its budget, which no longer binds (calm intervals
    # count through the hold, so the lift comes recover_intervals after the raise)
    lifted = [governor.observe(interval(300, 0.15, 5.0)) for _ in range(CONFIG.recover_intervals)]
    assert lifted[:-1] == [None] * (CONFIG.recover_intervals - 1)
    assert lifted[-1] is not None and lifted[-1].budget_hz is None
    assert "budget lifted" in lifted[-1].reason
    assert governor.budget_hz is None


def test_a_disabled_governor_measures_but_never_changes_the_budget() -> None:
    governor = OverloadGovernor(OverloadConfig(enabled=False))
    for _ in range(10):
        assert governor.observe(interval(1000, 1.0, 900.0)) is None
    assert governor.capacity_hz == pytest.approx(1000)
    assert governor.peak_latency_ms == 900.0


def test_rmax_for_budget_makes_the_fleet_rate_of_problem_6_equal_the_budget() -> None:
    topics = {"robot1": 7, "robot2": 7, "robot3": 6}
    rmin = 1.0
    budget = 600.0
    rmax = rmax_for_budget(budget, topics, rmin)
    solution = solve(QosLimits(rmax_hz=rmax, rmin_hz=rmin), list(topics.values()))
    fleet_rate = sum(topics.values()) * solution.rate_hz
    assert fleet_rate == pytest.approx(budget)


def test_a_budget_below_every_robots_minimum_leaves_them_at_rmin() -> None:
    topics = {"robot1": 7, "robot2": 7}
    rmax = rmax_for_budget(1.0, topics, 2.0)
    assert rmax == pytest.approx(2 * 2.0 * 7)
    assert solve(QosLimits(rmax_hz=rmax, rmin_hz=2.0), [7, 7]).rate_hz == pytest.approx(2.0)


def test_the_qos_controller_fits_its_assignment_to_the_budget() -> None:
    controller = QosController(QosControlConfig(enabled=True, rmax_hz=2100.0), "ceddp:x")
    topics = {"robot1": 7, "robot2": 7}
    free = controller.update(topics, "joined")
    assert free is not None and free.budget_hz is None
    assert free.robots["robot1"].rate_hz == pytest.approx(2100 / 7 - 1)
    controller.budget_hz = 560.0
    cut = controller.update(topics, "overload", force=True)
    assert cut is not None and cut.budget_hz == 560.0
    assert sum(7 * q.rate_hz for q in cut.robots.values()) == pytest.approx(560.0)
    # a budget larger than the configured limits allow changes nothing
    controller.budget_hz = 1e9
    roomy = controller.update(topics, "recovered", force=True)
    assert roomy is not None and roomy.robots == free.robots


def test_without_qos_control_a_budget_is_one_event_then_only_the_log() -> None:
    events: list[tuple[str, str]] = []
    config = CeddpConfig(fleet="f")
    worker = ControlWorker(
        config,
        Ingest("f", Planner(), CacheControl(enabled=True)),
        Downlink(MemoryTransport(MemoryBus()), "f", config),
        [],
        None,
        lambda text, level: events.append((text, level)),
    )
    for _ in range(3):
        worker._apply_budget(BudgetChange(500.0, "overload: measured capacity 625 samples/s"))
    assert worker.unapplied_budgets == 3
    assert len(events) == 1 and events[0][1] == "WARN"
    assert "QoS control is off" in events[0][0]
