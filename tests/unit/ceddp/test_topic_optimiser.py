"""The per-topic QoS optimiser: seed 001's answer when the topics are alike, hand-computed
weighted cases, the closed form against CVXPY and against the KKT conditions on random instances,
and the infeasible inputs. Expected values are computed by hand in the comments."""

from __future__ import annotations

import math
from fractions import Fraction

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from arpz.ceddp.optimiser import (
    FASTDDS_HEARTBEAT_PERIOD_S,
    InfeasibleQosError,
    InvalidQosInput,
    LinkQuality,
    QosLimits,
    channel_link,
    loss_aware_depth,
    solve_closed,
)
from arpz.ceddp.topic_optimiser import (
    AT_CEILING,
    AT_FLOOR,
    SHARE,
    TopicDemand,
    TopicSolution,
    effective_weight,
    solve_topics,
    solve_topics_closed,
    solve_topics_cvxpy,
)
from arpz.core.traffic import SENSOR_QOS


def _fleet(counts: list[int], **kwargs: object) -> list[TopicDemand]:
    return [
        TopicDemand(robot=f"robot{a}", topic=f"t{i}", **kwargs)  # type: ignore[arg-type]
        for a, count in enumerate(counts)
        for i in range(count)
    ]


# ------------------------------------------------------------------ the topics are all alike


@pytest.mark.parametrize("rmax", [100.0, 200.0, 500.0, 1000.0])
@pytest.mark.parametrize("counts", [[7, 6, 6], [6, 5, 5], [7, 6, 6, 6]])
def test_equal_weights_give_seed_001_exactly(rmax: float, counts: list[int]) -> None:
    limits = QosLimits(rmax_hz=rmax, rmin_hz=1.0)
    seed = solve_closed(limits, counts)
    ours = solve_topics_closed(limits, _fleet(counts, weight=2.5, change_hz=7.0))
    assert {t.rate_hz for t in ours.topics} == {seed.rate_hz}  # exactly, not approximately
    assert {t.depth for t in ours.topics} == {seed.depth}
    assert ours.used_hz == pytest.approx(ours.capacity_hz)


def test_paper_fleet_hand_computed() -> None:
    # T = 7,6,6, Rmax 100: C = 3 x 100 - 19 x 1 = 281; 281/19 = 14.789 Hz, D = 738
    solution = solve_topics_closed(QosLimits(rmax_hz=100, rmin_hz=1), _fleet([7, 6, 6]))
    assert solution.capacity_hz == 281
    assert solution.topics[0].rate_hz == 281 / 19
    assert solution.topics[0].depth == 738


@settings(max_examples=150, deadline=None)
@given(
    counts=st.lists(st.integers(1, 12), min_size=1, max_size=6),
    rmax=st.floats(10, 2000),
    rmin_share=st.floats(0.001, 0.2),
    dmax=st.integers(50, 10_000),
    weight=st.floats(0.01, 100),
)
def test_equal_weights_match_seed_001_on_random_fleets(
    counts: list[int], rmax: float, rmin_share: float, dmax: int, weight: float
) -> None:
    limits = QosLimits(rmax_hz=rmax, rmin_hz=rmax * rmin_share, dmax=dmax)
    try:
        seed = solve_closed(limits, counts)
    except InfeasibleQosError:
        with pytest.raises(InfeasibleQosError):
            solve_topics_closed(limits, _fleet(counts, weight=weight))
        return
    ours = solve_topics_closed(limits, _fleet(counts, weight=weight))
    assert all(t.rate_hz == seed.rate_hz and t.depth == seed.depth for t in ours.topics)


# ------------------------------------------------------------------ weighted, hand-computed


def test_weights_share_the_budget_in_proportion() -> None:
    # one robot, Rmax 100, Rmin 1: C = 100 - 2 = 98; weights 1 and 3 (change 1 Hz each):
    # r = 98/4 = 24.5 and 73.5; D = floor(50 r - 1) = 1224 and 3674
    limits = QosLimits(rmax_hz=100, rmin_hz=1)
    demands = [
        TopicDemand(robot="r", topic="pir", weight=1, change_hz=1),
        TopicDemand(robot="r", topic="lidar", weight=3, change_hz=1),
    ]
    solution = solve_topics_closed(limits, demands)
    assert solution.rate("r", "pir") == 24.5
    assert solution.rate("r", "lidar") == 73.5
    assert [t.depth for t in solution.topics] == [1224, 3674]
    assert solution.multiplier == 24.5


def test_change_rate_enters_as_a_square_root() -> None:
    # change 1 Hz and 16 Hz: weights 1 and 4: C = 98 -> 19.6 and 78.4 Hz
    limits = QosLimits(rmax_hz=100, rmin_hz=1)
    demands = [
        TopicDemand(robot="r", topic="pir", change_hz=1),
        TopicDemand(robot="r", topic="lidar", change_hz=16),
    ]
    solution = solve_topics_closed(limits, demands)
    assert solution.rate("r", "pir") == pytest.approx(19.6)
    assert solution.rate("r", "lidar") == pytest.approx(78.4)
    assert effective_weight(demands[1], 100) == 4


def test_floor_and_ceiling_bind() -> None:
    # two robots, Rmax 50, Rmin 5: C = 100 - 3 x 5 = 85. Weights 1, 1, 100: the heavy topic
    # would get 85 x 100/102 > Rmax, so it sits at its ceiling 50, the other two share 35
    # (17.5 each). With max_rate 10 on one light topic: it sits at 10, the other gets 25.
    limits = QosLimits(rmax_hz=50, rmin_hz=5, dmax=1000)
    demands = [
        TopicDemand(robot="a", topic="x", weight=1),
        TopicDemand(robot="a", topic="y", weight=1),
        TopicDemand(robot="b", topic="z", weight=100),
    ]
    solution = solve_topics_closed(limits, demands)
    assert [t.rate_hz for t in solution.topics] == [17.5, 17.5, 50.0]
    assert [t.bound for t in solution.topics] == [SHARE, SHARE, AT_CEILING]
    capped = [TopicDemand(robot="a", topic="x", weight=1, max_rate_hz=10), *demands[1:]]
    solution = solve_topics_closed(limits, capped)
    assert [t.rate_hz for t in solution.topics] == [10.0, 25.0, 50.0]
    # a tiny weight stays at the floor, max(Rmin, 2 Dmin Rmax/Dmax) = 5 Hz here
    light = [TopicDemand(robot="a", topic="x", weight=1e-6), *demands[1:]]
    assert solve_topics_closed(limits, light).topics[0].bound == AT_FLOOR


def test_costly_link_gets_fewer_samples() -> None:
    # cost 2 on robot b: C = 200 - 2 = 198 = r_a + 2 r_b with r_a = lambda, r_b = lambda/2
    # -> 2 lambda = 198: r_a = 99, r_b = 49.5
    limits = QosLimits(rmax_hz=100, rmin_hz=1)
    demands = [
        TopicDemand(robot="a", topic="t"),
        TopicDemand(robot="b", topic="t", cost=2.0),
    ]
    solution = solve_topics_closed(limits, demands)
    assert solution.rate("a", "t") == 99
    assert solution.rate("b", "t") == 49.5


# ------------------------------------------------------------------ closed form vs CVXPY


@st.composite
def _instances(draw: st.DrawFn) -> tuple[QosLimits, list[TopicDemand]]:
    rmax = draw(st.floats(20, 1000))
    limits = QosLimits(
        rmax_hz=rmax, rmin_hz=draw(st.floats(0.1, 2.0)), dmax=draw(st.integers(200, 5000))
    )
    robots = draw(st.integers(1, 4))
    demands = []
    for a in range(robots):
        cost = draw(st.floats(1.0, 2.0))
        for i in range(draw(st.integers(1, 6))):
            demands.append(
                TopicDemand(
                    robot=f"r{a}",
                    topic=f"t{i}",
                    weight=draw(st.floats(0.1, 10)),
                    change_hz=draw(st.one_of(st.none(), st.floats(0.05, 200))),
                    cost=cost,
                    max_rate_hz=draw(st.one_of(st.none(), st.floats(rmax / 4, rmax))),
                )
            )
    return limits, demands


#: found by hypothesis in CI: CVXPY's point used 6.7e-10 more than the capacity and had 1.0e-7
#: more utility than the closed form, within its tolerances, not a better optimum
_CVXPY_AHEAD = (
    QosLimits(rmax_hz=21.0, rmin_hz=1.875, dmax=200, dmin=1),
    [
        TopicDemand(robot=r, topic=t, weight=w, change_hz=None, cost=c, max_rate_hz=None)
        for r, t, w, c in [
            ("r0", "t0", 1.0, 1.0),
            *[("r1", f"t{i}", w, 1.0) for i, w in enumerate([1.0, 1.0, 3.0, 0.1])],
            *[("r2", f"t{i}", 1.0, 2.0) for i in range(6)],
            *[("r3", f"t{i}", 1.0, 1.75) for i in range(6)],
        ]
    ],
)

#: CI found CVXPY 2.2e-8 relative ahead of the exact optimum here (4.8e-7 of 21.64), beyond the
#: 1e-8 the test allowed then, with 8e-9 over the capacity
_CVXPY_AHEAD_2 = (
    QosLimits(rmax_hz=20.0, rmin_hz=1.5, dmax=200, dmin=1),
    [
        TopicDemand(robot="r0", topic=f"t{i}", weight=w, change_hz=None, cost=1.453125)
        for i, w in enumerate([1.0, 1.0, 4.0, 0.25, 0.25])
    ],
)


#: CI (a clean clone beside a busy loop, stop 40) found CLARABEL's status "optimal_inaccurate"
#: here: CVXPY's warning that says so raised out of the solve under ``-W error``. The optimiser
#: accepts that status on purpose; its rates agree with the exact ones to 2.3e-4
_CVXPY_INACCURATE = (
    QosLimits(rmax_hz=400.0, rmin_hz=1.7937936797820266, dmax=4655, dmin=1),
    [
        TopicDemand(robot=r, topic=t, weight=w, change_hz=ch, cost=c, max_rate_hz=mx)
        for r, t, w, ch, c, mx in [
            ("r0", "t0", 5.874276184176096, None, 1.756209269199121, None),
            ("r0", "t1", 9.12641911039699, None, 1.756209269199121, 150.0),
            ("r1", "t0", 6.630945842198559, None, 1.4302673809982656, None),
            ("r1", "t1", 2.2427641628905524, None, 1.4302673809982656, None),
            ("r1", "t2", 1.2725677480731572, 1.9, 1.4302673809982656, 272.58768712492497),
            ("r2", "t0", 7.867284789985021, None, 1.1043972555450288, 340.27051138566276),
            ("r2", "t1", 9.0, 97.93023486237914, 1.1043972555450288, 321.96285724561966),
            ("r2", "t2", 1.9489132976312966, 108.51501353110798, 1.1043972555450288, None),
            ("r2", "t3", 7.529796264599197, None, 1.1043972555450288, 375.06316514236926),
            ("r3", "t0", 0.1, None, 1.9617585990376478, None),
            ("r3", "t1", 2.2288547242022614, 38.905970306406616, 1.9617585990376478, None),
        ]
    ],
)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@example(_CVXPY_AHEAD)
@example(_CVXPY_AHEAD_2)
@example(_CVXPY_INACCURATE)
@given(_instances())
def test_closed_form_equals_cvxpy(instance: tuple[QosLimits, list[TopicDemand]]) -> None:
    limits, demands = instance
    try:
        closed = solve_topics_closed(limits, demands)
    except InfeasibleQosError:
        with pytest.raises(InfeasibleQosError):
            solve_topics_cvxpy(limits, demands)
        return
    cvx = solve_topics_cvxpy(limits, demands)
    # the solver's point is feasible and no better than the exact one: the exact optimum is
    # what CVXPY approaches (CLARABEL's interior point stops within about 1e-4 of the rates)
    weights = [t.weight for t in closed.topics]
    assert cvx.used_hz <= closed.capacity_hz * (1 + 1e-6)
    # CVXPY may overshoot the capacity by its feasibility tolerance and reports a point within
    # its optimality tolerance (seen in CI: 6.7e-10 over the capacity and 1.9e-9 relative more
    # utility than the exact optimum; 8e-9 over and 2.2e-8 more, _CVXPY_AHEAD_2). The optimum's
    # utility is concave in the capacity C with slope 1/lambda (r_i = lambda w_i / c_i for the
    # topics that share it), so overshooting by d buys at most d / lambda: the exact bound. (The
    # test used sum(w) log(1 + d/C), scaling every rate, which undercounts when topics held at
    # their floors take a share of C: CI found 6.3e-7 below against 5.5e-7 allowed.)
    over = max(0.0, cvx.used_hz - closed.capacity_hz)
    gain = 0.0 if closed.multiplier is None else over / closed.multiplier
    allowance = gain + 1e-7 * abs(_utility(closed, weights))
    assert _utility(closed, weights) >= _utility(cvx, weights) - allowance
    for a, b in zip(closed.topics, cvx.topics, strict=True):
        assert a.rate_hz == pytest.approx(b.rate_hz, rel=2e-3, abs=1e-4 * limits.rmax_hz)
        # the MILP's depth is the largest integer under (5) at the solver's own rate
        bound = limits.dmax * b.rate_hz / limits.rmax_hz - limits.dmin
        # (the MILP solver accepts a point within its feasibility tolerance, 1e-6 here)
        slack = 1 if abs(bound - round(bound)) < 1e-5 else 0
        assert abs(b.depth - min(limits.dmax, math.floor(bound + 1e-6))) <= slack


def _utility(solution: TopicSolution, weights: list[float]) -> float:
    return sum(w * math.log(t.rate_hz) for w, t in zip(weights, solution.topics, strict=True))


@settings(max_examples=200, deadline=None)
@given(_instances())
def test_closed_form_meets_the_kkt_conditions(
    instance: tuple[QosLimits, list[TopicDemand]],
) -> None:
    limits, demands = instance
    try:
        solution = solve_topics_closed(limits, demands)
    except InfeasibleQosError:
        return
    rmax, dmax, dmin = Fraction(limits.rmax_hz), limits.dmax, limits.dmin
    # feasibility, in the floats the solution reports
    used = sum(d.cost * t.rate_hz for d, t in zip(demands, solution.topics, strict=True))
    assert used <= solution.capacity_hz * (1 + 1e-12)
    for t in solution.topics:
        assert limits.rmin_hz * (1 - 1e-12) <= t.rate_hz <= limits.rmax_hz * (1 + 1e-12)
        assert dmin <= t.depth <= dmax
        # (5), forgiving 1e-6 of a sample as seed 001 does, and the rate's float rounding
        assert t.depth <= dmax * Fraction(t.rate_hz) / rmax - dmin + Fraction(2, 10**6)
        # the largest integer: one more sample would break (5)
        assert t.depth == dmax or t.depth + 1 > dmax * Fraction(t.rate_hz) / rmax - dmin
    # optimality: every topic that shares has the same lambda = r c / w; a topic at its floor
    # would get less at that lambda, one at its ceiling more
    lam = solution.multiplier
    if lam is None:
        assert all(t.bound == AT_CEILING for t in solution.topics)
        return
    for d, t in zip(demands, solution.topics, strict=True):
        want = lam * t.weight / d.cost
        if t.bound == SHARE:
            assert t.rate_hz == pytest.approx(want, rel=1e-9)
        elif t.bound == AT_FLOOR:
            assert want <= t.rate_hz * (1 + 1e-9)
        else:
            assert want >= t.rate_hz * (1 - 1e-9)
    # the budget is spent when it binds
    assert used == pytest.approx(solution.capacity_hz, rel=1e-9)


def test_solve_topics_dispatches_and_refuses_unknown_methods() -> None:
    limits, demands = QosLimits(rmax_hz=100, rmin_hz=1), _fleet([2])
    assert solve_topics(limits, demands).method == "closed"
    assert solve_topics(limits, demands, method="cvxpy").method == "cvxpy"
    with pytest.raises(InvalidQosInput, match="method"):
        solve_topics(limits, demands, method="simplex")  # type: ignore[arg-type]


# ------------------------------------------------------------------ bad and infeasible inputs


def test_infeasible_budget_names_the_constraint() -> None:
    # two robots of 30 topics at Rmax 50, Rmin 2: C = 100 - 120 < 0
    with pytest.raises(InfeasibleQosError, match=r"\(4\) sum_i c_i r_i") as info:
        solve_topics_closed(QosLimits(rmax_hz=50, rmin_hz=2), _fleet([30, 30]))
    assert "raise rmax_hz" in str(info.value)


def test_sensor_too_slow_for_the_floor_is_infeasible() -> None:
    with pytest.raises(InfeasibleQosError, match="max_rate_hz"):
        solve_topics_closed(
            QosLimits(rmax_hz=100, rmin_hz=5),
            [TopicDemand(robot="a", topic="slow", max_rate_hz=2)],
        )


@pytest.mark.parametrize(
    ("field", "value"),
    [("weight", 0.0), ("weight", math.nan), ("change_hz", -1.0), ("cost", 0.5)],
)
def test_bad_demand_names_the_field(field: str, value: float) -> None:
    with pytest.raises(InvalidQosInput, match=field):
        TopicDemand(robot="a", topic="t", **{field: value})  # type: ignore[arg-type]


def test_duplicate_and_empty_topics_are_refused() -> None:
    limits = QosLimits(rmax_hz=100, rmin_hz=1)
    with pytest.raises(InvalidQosInput, match="twice"):
        solve_topics_closed(limits, _fleet([1]) + _fleet([1]))
    with pytest.raises(InvalidQosInput, match="no topics"):
        solve_topics_closed(limits, [])


# ------------------------------------------------------------------ the channel's own timings


def test_loss_aware_depth_uses_the_channel_in_force() -> None:
    # 10 % loss, 20 ms RTT: k = 9 rounds (docs/qos-optimiser.md). arpz's sensor profile:
    # heartbeat 0.1 s, NACK delay 2 ms -> round 0.122 s, hold 1.098 s; at 17.75 Hz
    # D = ceil(19.49) = 20, against 484 with Fast DDS's 3 s heartbeat
    link = channel_link(SENSOR_QOS, rtt_s=0.02, loss_pct=10)
    assert link.heartbeat_period_s == 0.1 and link.nack_delay_s == 0.002
    ours = loss_aware_depth(link, 17.75)
    assert ours.rounds == 9
    assert ours.round_s == pytest.approx(0.122)
    assert ours.depth == 20
    fastdds = loss_aware_depth(LinkQuality(rtt_s=0.02, loss_pct=10), 17.75)
    assert FASTDDS_HEARTBEAT_PERIOD_S == 3.0 and fastdds.depth == 484


def test_a_measured_burst_adds_its_samples() -> None:
    # the same link with bursts of 4.2 samples: 20 + ceil(4.2) = 25
    link = channel_link(SENSOR_QOS, rtt_s=0.02, loss_pct=10, burst_samples=4.2)
    assert loss_aware_depth(link, 17.75).depth == 25
    clean = channel_link(SENSOR_QOS, rtt_s=0.02, loss_pct=0, burst_samples=4.2)
    assert loss_aware_depth(clean, 17.75).depth == 1  # nothing to recover, no burst either
