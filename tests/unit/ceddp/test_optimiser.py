"""The QoS balancing optimiser (seed 001, problem 6): hand-computed cases, agreement of the
closed form with CVXPY, infeasibility messages and the loss-aware depth.

Expected values are computed by hand in the comments (exact fractions), never copied from a run.
"""

from __future__ import annotations

import math
from fractions import Fraction

import msgspec
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from arpz.ceddp.optimiser import (
    DEPTH_BALANCE,
    DEPTH_MAX,
    DEPTH_MIN,
    RATE_BALANCE,
    RATE_MAX,
    RATE_MIN,
    InfeasibleQosError,
    InvalidQosInput,
    LinkQuality,
    QosLimits,
    assign_qos,
    average_topics,
    loss_aware_depth,
    solve,
    solve_closed,
    solve_cvxpy,
)

# ---------------------------------------------------------------- hand-computed paper settings
# Rmin = 1 Hz, Dmin = 1, Dmax = 5000 throughout. The optimum is R* = Rmax/T_avg - Rmin and
# D* = floor(Dmax R*/Rmax - Dmin) = floor(Dmax/T_avg - Dmax Rmin/Rmax - Dmin).
#
# Sensor topics only (machine 1: 6 sensors, machines 2 and 3: 5): T = 6,5,5, T_avg = 16/3.
#   Rmax  100: R = 300/16 - 1 = 17.75     D = floor(937.5 - 50 - 1) = floor(886.5) = 886
#   Rmax  200: R = 600/16 - 1 = 36.5      D = floor(937.5 - 25 - 1) = 911
#   Rmax  500: R = 1500/16 - 1 = 92.75    D = floor(937.5 - 10 - 1) = 926
#   Rmax 1000: R = 3000/16 - 1 = 186.5    D = floor(937.5 - 5 - 1)  = 931
# Eq. 1 counts the received localisation/command topic too: T = 7,6,6, T_avg = 19/3,
# Dmax/T_avg = 15000/19 = 789.47...
#   Rmax  100: R = 300/19 - 1 = 281/19    D = floor(789.47 - 50 - 1) = 738
#   Rmax  200: R = 600/19 - 1 = 581/19    D = floor(789.47 - 25 - 1) = 763
#   Rmax  500: R = 1500/19 - 1 = 1481/19  D = floor(789.47 - 10 - 1) = 778
#   Rmax 1000: R = 3000/19 - 1 = 2981/19  D = floor(789.47 - 5 - 1)  = 783
PAPER_CASES = [
    ((6, 5, 5), 100, Fraction(71, 4), 886),
    ((6, 5, 5), 200, Fraction(73, 2), 911),
    ((6, 5, 5), 500, Fraction(371, 4), 926),
    ((6, 5, 5), 1000, Fraction(373, 2), 931),
    ((7, 6, 6), 100, Fraction(281, 19), 738),
    ((7, 6, 6), 200, Fraction(581, 19), 763),
    ((7, 6, 6), 500, Fraction(1481, 19), 778),
    ((7, 6, 6), 1000, Fraction(2981, 19), 783),
]


@pytest.mark.parametrize(("topics", "rmax_hz", "rate", "depth"), PAPER_CASES)
def test_paper_settings_closed_form(
    topics: tuple[int, ...], rmax_hz: int, rate: Fraction, depth: int
) -> None:
    result = solve_closed(QosLimits(rmax_hz=rmax_hz, rmin_hz=1), list(topics))
    assert result.rate_hz == pytest.approx(float(rate), rel=1e-12)
    assert result.deadline_s == pytest.approx(float(1 / rate), rel=1e-12)
    assert result.depth == depth
    assert result.t_avg == pytest.approx(sum(topics) / 3)
    # R sits on (4); D is the largest integer under (5); nothing else holds the optimum.
    assert set(result.binding) == {RATE_BALANCE, DEPTH_BALANCE}
    assert result.method == "closed"


@pytest.mark.parametrize(("topics", "rmax_hz", "rate", "depth"), PAPER_CASES)
def test_paper_settings_cvxpy(
    topics: tuple[int, ...], rmax_hz: int, rate: Fraction, depth: int
) -> None:
    result = solve_cvxpy(QosLimits(rmax_hz=rmax_hz, rmin_hz=1), list(topics))
    assert result.rate_hz == pytest.approx(float(rate), abs=1e-6 * rmax_hz)
    assert result.depth == depth
    assert set(result.binding) == {RATE_BALANCE, DEPTH_BALANCE}
    assert result.method == "cvxpy"


@pytest.mark.parametrize("method", ["closed", "cvxpy"])
def test_corner_where_lower_bounds_bind_too(method: str) -> None:
    # T = 5,5,5, Rmax 100, Rmin 10: R = 100/5 - 10 = 10 = Rmin, so R >= Rmin binds as well.
    # Dmax R / Rmax = 5000 * 10 / 100 = 500 exactly; with Dmin 1, D = 499 and (5) has slack 0.
    result = solve(QosLimits(rmax_hz=100, rmin_hz=10), [5, 5, 5], method=method)  # type: ignore[arg-type]
    assert result.rate_hz == pytest.approx(10, abs=1e-4)
    assert result.depth == 499
    assert set(result.binding) == {RATE_BALANCE, DEPTH_BALANCE, RATE_MIN}
    # Dmin 250: D = floor(500 - 250) = 250 = Dmin, so D >= Dmin binds too.
    result = solve(QosLimits(rmax_hz=100, rmin_hz=10, dmin=250), [5, 5, 5], method=method)  # type: ignore[arg-type]
    assert result.depth == 250
    assert set(result.binding) == {RATE_BALANCE, DEPTH_BALANCE, RATE_MIN, DEPTH_MIN}


def test_single_agent_single_topic() -> None:
    # T_avg = 1: R = Rmax - Rmin = 90 of 100 Hz, D = floor(5000 * 0.9 - 1) = 4499.
    result = solve_closed(QosLimits(rmax_hz=100, rmin_hz=10), [1])
    assert result.rate_hz == 90
    assert result.depth == 4499
    assert RATE_MAX not in result.binding
    assert DEPTH_MAX not in result.binding


# ---------------------------------------------------------------- infeasibility messages
def test_rate_bound_infeasible_names_bound_and_fixes() -> None:
    # T_avg = 6, Rmax 480: Rmax/T_avg - Rmin = 80 - 50 = 30 < Rmin = 50. Feasible iff
    # Rmax/T_avg >= 2 Rmin: Rmax >= 2*50*6 = 600, or Rmin <= 480/12 = 40.
    with pytest.raises(InfeasibleQosError) as caught:
        solve_closed(QosLimits(rmax_hz=480, rmin_hz=50), [6, 6, 6])
    error = caught.value
    message = str(error)
    assert error.constraint == RATE_BALANCE
    assert "= 30 < Rmin = 50" in message
    assert "raise Rmax to at least 600 Hz" in message
    assert "lower Rmin to at most 40 Hz" in message
    assert error.lhs == 30 and error.rhs == 50
    assert {(s.parameter, s.value) for s in error.suggestions} == {
        ("rmax_hz", 600.0),
        ("rmin_hz", 40.0),
    }


def test_rate_fix_rounds_in_the_safe_direction() -> None:
    # T_avg = 3, Rmax 100, Rmin 20: 33.3 - 20 < 20. Rmin <= 100/6 = 16.666... -> "16.6" (down);
    # Rmax >= 2*20*3 = 120 exactly.
    with pytest.raises(InfeasibleQosError) as caught:
        solve_closed(QosLimits(rmax_hz=100, rmin_hz=20), [3])
    assert "lower Rmin to at most 16.6 Hz" in str(caught.value)
    assert "raise Rmax to at least 120 Hz" in str(caught.value)


def test_depth_bound_infeasible_names_bound_and_fixes() -> None:
    # T = 5,5,5, Rmax 100, Rmin 10 -> R = 10; Dmax R/Rmax = 500, Dmin 300: 500 - 300 = 200 < 300.
    # Fixes (need Dmax R/Rmax >= 2 Dmin = 600): Dmax >= 600*100/10 = 6000; Dmin <= 250;
    # Rmin <= Rmax/T_avg - 2 Dmin Rmax/Dmax = 20 - 12 = 8; Rmax >= Rmin/(1/5 - 600/5000) = 125.
    with pytest.raises(InfeasibleQosError) as caught:
        solve_closed(QosLimits(rmax_hz=100, rmin_hz=10, dmin=300), [5, 5, 5])
    error = caught.value
    assert error.constraint == DEPTH_BALANCE
    assert "200 < Dmin = 300" in str(error)
    assert {(s.parameter, s.bound, s.value) for s in error.suggestions} == {
        ("dmax", "at least", 6000.0),
        ("dmin", "at most", 250.0),
        ("rmin_hz", "at most", 8.0),
        ("rmax_hz", "at least", 125.0),
    }


def test_cvxpy_raises_the_same_clear_error() -> None:
    with pytest.raises(InfeasibleQosError, match="raise Rmax to at least 600 Hz"):
        solve_cvxpy(QosLimits(rmax_hz=480, rmin_hz=50), [6, 6, 6])


# ---------------------------------------------------------------- input validation
@pytest.mark.parametrize(
    ("kwargs", "fragment"),
    [
        ({"rmax_hz": 0, "rmin_hz": 1}, "rmax_hz must be a finite rate > 0"),
        ({"rmax_hz": 100, "rmin_hz": -1}, "rmin_hz must be a finite rate > 0"),
        ({"rmax_hz": math.nan, "rmin_hz": 1}, "rmax_hz"),
        ({"rmax_hz": 100, "rmin_hz": 1, "dmin": 0}, "dmin must be >= 1"),
        ({"rmax_hz": 100, "rmin_hz": 1, "dmin": 10, "dmax": 5}, "dmin = 10 is above dmax = 5"),
        ({"rmax_hz": 10, "rmin_hz": 20}, "rmin_hz = 20 Hz is above rmax_hz = 10 Hz"),
        ({"rmax_hz": 100, "rmin_hz": 1, "dmax": 10.5}, "dmax must be an integer"),
    ],
)
def test_invalid_limits(kwargs: dict[str, float], fragment: str) -> None:
    with pytest.raises(InvalidQosInput, match=fragment):
        QosLimits(**kwargs)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("topics", "fragment"),
    [([], "topic list is empty"), ([3, 0], "agent 1 must be an integer >= 1"), ([2.5], "agent 0")],
)
def test_invalid_topics(topics: list[int], fragment: str) -> None:
    with pytest.raises(InvalidQosInput, match=fragment):
        solve_closed(QosLimits(rmax_hz=100, rmin_hz=1), topics)


def test_limits_load_from_toml_like_data() -> None:
    limits = msgspec.convert({"rmax_hz": 200, "rmin_hz": 5}, QosLimits)
    assert (limits.dmax, limits.dmin) == (5000, 1)
    with pytest.raises(msgspec.ValidationError, match="rmax_hx"):
        msgspec.convert({"rmax_hx": 200, "rmax_hz": 200, "rmin_hz": 5}, QosLimits)
    with pytest.raises(msgspec.ValidationError, match="dmin = 9 is above dmax = 8"):
        msgspec.convert({"rmax_hz": 200, "rmin_hz": 5, "dmax": 8, "dmin": 9}, QosLimits)


# ---------------------------------------------------------------- properties
topic_lists = st.lists(st.integers(min_value=1, max_value=40), min_size=1, max_size=12)


@st.composite
def limit_inputs(draw: st.DrawFn) -> tuple[QosLimits, list[int]]:
    rmax = draw(st.floats(min_value=1.0, max_value=1e4, allow_nan=False))
    rmin = draw(st.floats(min_value=1e-3, max_value=rmax))
    dmax = draw(st.integers(min_value=1, max_value=20000))
    dmin = draw(st.integers(min_value=1, max_value=dmax))
    return QosLimits(rmax_hz=rmax, rmin_hz=rmin, dmax=dmax, dmin=dmin), draw(topic_lists)


def _check_optimal_by_the_problem_statement(limits: QosLimits, topics: list[int]) -> None:
    """Checks problem (6) itself in exact arithmetic, independently of how R* and D* were found:
    (R*, D*) is feasible, no larger R is, and D* + 1 is not feasible at R*."""
    result = solve_closed(limits, topics)
    t_avg = Fraction(sum(topics), len(topics))
    rate, depth = Fraction(result.rate_hz), result.depth
    rmax, rmin = Fraction(limits.rmax_hz), Fraction(limits.rmin_hz)
    dmax, dmin = limits.dmax, limits.dmin
    scale = rmax * Fraction(1, 10**12)  # float rounding of R* when it is reported
    tol = Fraction(1, 10**6)  # documented: D may exceed (5) by 1e-6 sample (float inputs)
    assert rmax / t_avg - rate >= rmin - scale
    assert dmax * rate / rmax - depth >= dmin - tol - dmax * scale / rmax
    assert rmin - scale <= rate <= rmax
    assert dmin <= depth <= dmax
    assert rmax / t_avg - (rate + 2 * scale) < rmin  # any larger R breaks (4)
    beyond = dmax * rate / rmax - (depth + 1) < dmin - tol + dmax * scale / rmax
    assert beyond or depth + 1 > dmax


@given(limit_inputs())
@settings(max_examples=300, deadline=None)
def test_closed_form_is_optimal_or_raises_the_clear_error(
    inputs: tuple[QosLimits, list[int]],
) -> None:
    limits, topics = inputs
    try:
        _check_optimal_by_the_problem_statement(limits, topics)
    except InfeasibleQosError as error:
        # Infeasible must mean it: even R = Rmin with D = Dmin breaks (4) or (5).
        t_avg = Fraction(sum(topics), len(topics))
        rmax, rmin = Fraction(limits.rmax_hz), Fraction(limits.rmin_hz)
        best_rate = rmax / t_avg - rmin
        room = limits.dmax * best_rate / rmax - limits.dmin + Fraction(1, 10**6)
        assert best_rate < rmin or room < limits.dmin, "declared infeasible but is feasible"
        assert "infeasible" in str(error) and error.constraint in (RATE_BALANCE, DEPTH_BALANCE)
        assert bool(error.suggestions) != bool(error.together)
        if error.together:  # no single change works, so all of them together must
            fields = msgspec.structs.asdict(limits)
            for s in error.together:
                fields[s.parameter] = int(s.value) if s.parameter.startswith("d") else s.value
            solve_closed(QosLimits(**fields), topics)


def test_two_changes_when_no_single_one_helps() -> None:
    # T = 1, Rmax 1, Rmin 1, Dmax 1: (4) fails (1 - 1 < 1) and (5) can never hold with Dmax 1
    # (D <= Dmax R/Rmax - Dmin <= 0). Rmin <= 1/2 gives R = 1/2; then Dmax >= 2*1*1/(1/2) = 4.
    with pytest.raises(InfeasibleQosError) as caught:
        solve_closed(QosLimits(rmax_hz=1, rmin_hz=1, dmax=1, dmin=1), [1])
    assert caught.value.suggestions == ()
    assert "lower Rmin to at most 0.5 Hz and raise Dmax to at least 4 samples" in str(caught.value)


@st.composite
def infeasible_inputs(draw: st.DrawFn) -> tuple[QosLimits, list[int]]:
    limits, topics = draw(limit_inputs())
    try:
        solve_closed(limits, topics)
    except InfeasibleQosError:
        return limits, topics
    assume(False)
    raise AssertionError  # pragma: no cover


@given(infeasible_inputs())
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
def test_each_suggestion_fixes_and_is_the_smallest(inputs: tuple[QosLimits, list[int]]) -> None:
    limits, topics = inputs
    with pytest.raises(InfeasibleQosError) as caught:
        solve_closed(limits, topics)
    fields = msgspec.structs.asdict(limits)
    for suggestion in caught.value.suggestions:
        value: float = suggestion.value
        if suggestion.parameter in ("dmax", "dmin"):
            value = int(value)
        fixed = QosLimits(**{**fields, suggestion.parameter: value})
        solve_closed(fixed, topics)  # must not raise
        # "Smallest": 2 % (beyond the 3-significant-digit display rounding) or one sample
        # less of the change is still infeasible.
        if suggestion.parameter in ("dmax", "dmin"):
            worse: float = value - 1 if suggestion.bound == "at least" else value + 1
        else:
            worse = value * (0.98 if suggestion.bound == "at least" else 1.02)
        try:
            unfixed = QosLimits(**{**fields, suggestion.parameter: worse})
        except InvalidQosInput:
            continue  # e.g. Dmax - 1 < Dmin: not a valid input at all
        with pytest.raises(InfeasibleQosError):
            solve_closed(unfixed, topics)


@st.composite
def feasible_inputs(draw: st.DrawFn) -> tuple[QosLimits, list[int]]:
    topics = draw(st.lists(st.integers(min_value=1, max_value=20), min_size=1, max_size=8))
    t_avg = sum(topics) / len(topics)
    rmax = draw(st.floats(min_value=10.0, max_value=5000.0))
    # Rmin below Rmax/(2 T_avg) keeps (4) feasible; Dmin below a quarter of Dmax R/Rmax keeps (5).
    rmin = draw(st.floats(min_value=0.01, max_value=rmax / (2 * t_avg)))
    dmax = draw(st.integers(min_value=50, max_value=20000))
    room = dmax * (1 / t_avg - rmin / rmax)
    assume(room >= 2)
    dmin = draw(st.integers(min_value=1, max_value=max(1, int(room // 2))))
    limits = QosLimits(rmax_hz=rmax, rmin_hz=rmin, dmax=dmax, dmin=dmin)
    try:  # the float bounds above can land one ulp on the wrong side of the exact ones
        solve_closed(limits, topics)
    except InfeasibleQosError:
        assume(False)
    return limits, topics


@given(feasible_inputs())
@settings(max_examples=60, deadline=None)
def test_closed_form_and_cvxpy_agree(inputs: tuple[QosLimits, list[int]]) -> None:
    limits, topics = inputs
    closed = solve_closed(limits, topics)
    cvx = solve_cvxpy(limits, topics)
    assert cvx.rate_hz == pytest.approx(closed.rate_hz, abs=1e-6 * limits.rmax_hz)
    assert cvx.depth == closed.depth
    assert cvx.binding == closed.binding


@given(
    feasible_inputs(),
    st.floats(min_value=1e-3, max_value=1e3),
    st.floats(min_value=1e-3, max_value=1e3),
)
@settings(max_examples=8, deadline=None)
def test_any_positive_weighted_sum_reaches_the_lexicographic_optimum(
    inputs: tuple[QosLimits, list[int]], w_rate: float, w_depth: float
) -> None:
    # Why lexicographic loses nothing: (5) loosens as R grows, so there is no trade-off.
    limits, topics = inputs
    closed = solve_closed(limits, topics)
    weighted = solve_cvxpy(limits, topics, weights=(w_rate, w_depth))
    assert weighted.rate_hz == pytest.approx(closed.rate_hz, abs=1e-6 * limits.rmax_hz)
    assert weighted.depth == closed.depth


def test_float_noise_does_not_cost_a_sample() -> None:
    # Rmin = Rmax/28 with T = 1, Dmax 56: R/Rmax = 27/28, Dmax R/Rmax = 54 in exact decimal
    # arithmetic, so D = 54 - 1 = 53, although the binary floats give 53.99999999999999.
    rmax = 206.87648770030054
    limits = QosLimits(rmax_hz=rmax, rmin_hz=7.388445989296448, dmax=56, dmin=1)
    assert Fraction(56) * (1 - Fraction(limits.rmin_hz) / Fraction(rmax)) < 54  # real noise
    assert solve_closed(limits, [1]).depth == 53
    assert solve_cvxpy(limits, [1]).depth == 53


def test_average_topics_is_exact() -> None:
    assert average_topics([7, 6, 6]) == Fraction(19, 3)


# ---------------------------------------------------------------- loss-aware depth
def test_loss_aware_depth_fast_dds_defaults_ten_percent() -> None:
    # p = 0.1: q = 1 - 0.9^3 = 0.271. Need 0.1 * 0.271^k <= 1e-6, i.e. 0.271^k <= 1e-5:
    # k >= ln(1e-5)/ln(0.271) = 11.513/1.3056 = 8.82 -> k = 9 (0.1*0.271^9 = 7.9e-7).
    # Round = 3 s heartbeat + 5 ms NACK delay + 20 ms RTT = 3.025 s; hold 9 * 3.025 = 27.225 s.
    # At R = 17.75 Hz (paper, Rmax 100, T 6,5,5): ceil(17.75 * 27.225) = ceil(483.24) = 484.
    result = loss_aware_depth(LinkQuality(rtt_s=0.020, loss_pct=10), 17.75)
    assert result.rounds == 9
    assert result.round_s == pytest.approx(3.025)
    assert result.hold_s == pytest.approx(27.225)
    assert result.depth == 484
    assert 7.8e-7 < result.residual_loss < 8.0e-7


def test_loss_aware_depth_one_percent_and_cyclone_timings() -> None:
    # p = 0.01: q = 1 - 0.99^3 = 0.029701; 0.01 q^k <= 1e-6 -> q^k <= 1e-4 -> k >= 2.62 -> 3.
    # Hold 3 * 3.025 = 9.075 s; at 100 Hz: ceil(907.5) = 908.
    assert loss_aware_depth(LinkQuality(rtt_s=0.02, loss_pct=1), 100).depth == 908
    # Cyclone DDS: heartbeat 100 ms, NackDelay 100 ms -> round 0.22 s; 10 % -> 9 rounds, 1.98 s;
    # at 186.5 Hz: ceil(369.27) = 370.
    cyclone = LinkQuality(rtt_s=0.02, loss_pct=10, heartbeat_period_s=0.1, nack_delay_s=0.1)
    assert loss_aware_depth(cyclone, 186.5).depth == 370


def test_loss_aware_depth_lossless_link_needs_one_sample() -> None:
    result = loss_aware_depth(LinkQuality(rtt_s=0.05, loss_pct=0), 1000)
    assert (result.rounds, result.depth, result.hold_s) == (0, 1, 0)


@given(
    st.floats(min_value=0.01, max_value=60),
    st.floats(min_value=0, max_value=500),
    st.floats(min_value=0.1, max_value=2000),
)
@settings(max_examples=200)
def test_loss_aware_depth_holds_the_sample_exactly_long_enough(
    loss_pct: float, rtt_ms: float, rate_hz: float
) -> None:
    link = LinkQuality(rtt_s=rtt_ms / 1000, loss_pct=loss_pct)
    result = loss_aware_depth(link, rate_hz)
    p = loss_pct / 100
    q = 1 - (1 - p) ** 3
    assert p * q**result.rounds <= 1e-6
    assert result.rounds == 0 or p * q ** (result.rounds - 1) > 1e-6
    # D samples at R Hz last D/R s: enough, and one sample fewer would not be.
    assert result.depth / rate_hz >= result.hold_s * (1 - 1e-12)
    assert result.depth == 1 or (result.depth - 1) / rate_hz < result.hold_s


@pytest.mark.parametrize(
    ("kwargs", "fragment"),
    [
        ({"rtt_s": 0.02, "loss_pct": 100}, r"loss_pct must be in \[0, 100\)"),
        ({"rtt_s": -1, "loss_pct": 1}, "rtt_s must be a finite time >= 0"),
        ({"rtt_s": 0.02, "loss_pct": 1, "residual_loss": 0}, "residual_loss"),
    ],
)
def test_invalid_link(kwargs: dict[str, float], fragment: str) -> None:
    with pytest.raises(InvalidQosInput, match=fragment):
        LinkQuality(**kwargs)


# ---------------------------------------------------------------- the live-control entry point
FLEET = {"robot1": 6, "robot2": 5, "robot3": 5}
LOSSY = LinkQuality(rtt_s=0.02, loss_pct=10)  # needs 27.225 s of history (see above)


def test_assign_qos_paper_policy_reports_loss_safety() -> None:
    # Rmax 100: R = 17.75, D = 886; loss-aware 484 <= 886, so the paper's D is loss-safe.
    result = assign_qos(QosLimits(rmax_hz=100, rmin_hz=1), FLEET, link=LOSSY)
    assert (result.depth, result.paper_depth) == (886, 886)
    assert result.loss is not None and result.loss.depth == 484
    assert result.loss_safe is True and result.paper_loss_safe is True
    assert result.topics_per_agent == FLEET
    assert result.deadline_s == pytest.approx(1 / 17.75)


def test_assign_qos_max_policy_caps_at_dmax() -> None:
    # Rmax 1000: R = 186.5, paper D = 931; loss-aware ceil(186.5 * 27.225) = ceil(5077.46) = 5078
    # > Dmax 5000: "max" applies 5000 and says it is still not loss-safe.
    limits = QosLimits(rmax_hz=1000, rmin_hz=1)
    result = assign_qos(limits, FLEET, depth_policy="max", link=LOSSY)
    assert result.loss is not None and result.loss.depth == 5078
    assert (result.depth, result.paper_depth) == (5000, 931)
    assert result.loss_safe is False and result.paper_loss_safe is False
    # "loss_aware" with a lossless link: the loss-aware depth is 1 sample, clamped up to Dmin.
    clean = LinkQuality(rtt_s=0.02, loss_pct=0)
    limits = QosLimits(rmax_hz=1000, rmin_hz=1, dmin=4)
    result = assign_qos(limits, FLEET, depth_policy="loss_aware", link=clean)
    assert result.depth == 4 and result.loss_safe is True


def test_assign_qos_max_policy_keeps_paper_depth_when_larger() -> None:
    result = assign_qos(QosLimits(rmax_hz=100, rmin_hz=1), FLEET, depth_policy="max", link=LOSSY)
    assert result.depth == 886


def test_assign_qos_rejects_policy_without_link_and_unknown_policy() -> None:
    limits = QosLimits(rmax_hz=100, rmin_hz=1)
    with pytest.raises(InvalidQosInput, match="needs the link quality"):
        assign_qos(limits, FLEET, depth_policy="max")
    with pytest.raises(InvalidQosInput, match="depth_policy must be one of"):
        assign_qos(limits, FLEET, depth_policy="biggest")  # type: ignore[arg-type]
    with pytest.raises(InvalidQosInput, match="topic list is empty"):
        assign_qos(limits, {})


def test_assignment_is_a_frozen_struct_that_encodes() -> None:
    result = assign_qos(QosLimits(rmax_hz=200, rmin_hz=1), FLEET)
    decoded = msgspec.json.decode(msgspec.json.encode(result))
    assert decoded["depth"] == 911 and decoded["rate_hz"] == 36.5
    with pytest.raises(AttributeError):
        result.depth = 1  # type: ignore[misc]


def test_paper_depth_is_not_loss_safe_at_200_hz_with_fast_dds_heartbeats() -> None:
    # T = 7,6,6, Rmax 200: R = 581/19 = 30.579 Hz, D = 763 (table above); its history lasts
    # 763/30.579 = 24.95 s < 27.225 s needed at 10 % loss: ceil(30.579 * 27.225) = 833 > 763.
    fleet = {"robot1": 7, "robot2": 6, "robot3": 6}
    result = assign_qos(QosLimits(rmax_hz=200, rmin_hz=1), fleet, depth_policy="max", link=LOSSY)
    assert result.loss is not None and result.loss.depth == 833
    assert result.paper_depth == 763 and result.paper_loss_safe is False
    assert result.depth == 833 and result.loss_safe is True
