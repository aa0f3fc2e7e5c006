"""Per-topic QoS: a rate and a depth for each topic, from what each topic needs (issue 20).

Seed 001 (problem 6, ``arpz.ceddp.optimiser``) gives every topic of the fleet one rate R and one
depth D. A PIR sensor that changes once a minute and a LIDAR that changes every scan then get
the same share of the budget. This module shares the same budget between the topics by what
they are worth. Pure logic: values in, values out (no Zenoh, no Rerun).

The problem, for topics i = 1..N of A robots (N counts every topic of eq. 1)::

    max  sum_i w_i log r_i                               weighted sum of (log) rates
    s.t. sum_i c_i r_i <= C,  C = A Rmax - N Rmin        (4) summed over the topics
         Dmax r_i / Rmax - d_i >= Dmin                   (5) for each topic
         Rmin <= r_i <= min(Rmax, max_rate_i),  Dmin <= d_i <= Dmax,  d_i integer

- ``w_i = priority_i * sqrt(change_hz_i)``: the topic's priority (config) times the square root
  of how often its value changes (measured by the robot's local cache). With an equal cost, the
  optimum gives r_i proportional to w_i, and r proportional to sqrt(change) is what minimises
  the fleet's summed staleness sum_i change_i / (2 r_i) under the same budget.
- ``c_i`` (>= 1) is how many transmissions one sample of the topic costs on its robot's link
  (1 + the measured resends per sample): a lossy link spends more of the budget per sample.
- The capacity C is eq. (4), Rmax/T_avg - R >= Rmin, written for every topic and summed: with
  all weights and costs equal, every topic gets exactly seed 001's R* = Rmax/T_avg - Rmin and
  D* (tested against ``solve_closed``). With an overload budget B, Rmax is the one
  ``rmax_for_budget`` gives, so C = B.
- Why log: a *linear* weighted sum of rates is maximised at a vertex (the heaviest topics at
  Rmax, the others starved at Rmin), and with equal weights every split is optimal, so it could
  not promise seed 001's answer. The log makes the optimum unique and keeps every topic above its
  floor in proportion to its weight.
- Depths decouple once the rates are known (the only coupling, (5), loosens as r_i grows):
  d_i = floor(Dmax r_i/Rmax - Dmin), lexicographic as in seed 001. A topic's rate therefore may
  not go below 2 Dmin Rmax / Dmax, where (5) still admits d_i = Dmin.

``solve_topics_closed`` is the exact water-filling solution (KKT: r_i = clamp(lambda w_i / c_i,
lo_i, hi_i) with lambda set so the budget is spent), in rational arithmetic; ``solve_topics_cvxpy``
states the problem in CVXPY (an exponential-cone program for the rates, then a MILP for the
integer depths). They agree (tests/unit/ceddp/test_topic_optimiser.py, hypothesis).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from fractions import Fraction
from typing import Any, Final, Literal

import msgspec

from arpz.ceddp.optimiser import (
    _SOLVED,
    InfeasibleQosError,
    InvalidQosInput,
    OptimiserError,
    QosLimits,
    _best_depth,
    _solve,
)

TopicMethod = Literal["closed", "cvxpy"]
TOPIC_METHODS: Final[tuple[str, ...]] = ("closed", "cvxpy")
CAPACITY: Final = "(4) sum_i c_i r_i <= A Rmax - N Rmin"
#: where a topic's rate sits at the optimum
AT_FLOOR, AT_CEILING, SHARE, FIXED = "floor", "ceiling", "share", "fixed"


class TopicDemand(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """One topic of the per-topic problem: whose it is and what it is worth."""

    robot: str
    topic: str
    #: the config's priority (> 0); 1 for every topic gives seed 001's answer
    weight: float = 1.0
    #: how often the value changes (Hz, > 0), as the local cache counts it; None: not known,
    #: then the topic counts as changing at every sample (change factor sqrt(Rmax))
    change_hz: float | None = None
    #: transmissions per sample on the robot's link (>= 1): 1 + measured resends per sample
    cost: float = 1.0
    #: the fastest the sensor can be read (its ``max_rate_hz``); None: only Rmax bounds it
    max_rate_hz: float | None = None
    #: a topic whose rate is not the optimiser's to set (a command the robot receives, eq. 1):
    #: it takes exactly this rate's share of the budget (the live CEDDP gives it seed 001's R)
    fixed_hz: float | None = None

    def __post_init__(self) -> None:
        where = f"topic {self.topic!r} of robot {self.robot!r}"
        if not (math.isfinite(self.weight) and self.weight > 0):
            raise InvalidQosInput(f"{where}: weight must be a finite number > 0, got {self.weight}")
        if self.change_hz is not None and not (
            math.isfinite(self.change_hz) and self.change_hz > 0
        ):
            raise InvalidQosInput(
                f"{where}: change_hz must be a finite rate > 0 Hz, got {self.change_hz}"
            )
        if not (math.isfinite(self.cost) and self.cost >= 1):
            raise InvalidQosInput(f"{where}: cost must be >= 1 transmission, got {self.cost}")
        if self.fixed_hz is not None and not (math.isfinite(self.fixed_hz) and self.fixed_hz > 0):
            raise InvalidQosInput(
                f"{where}: fixed_hz must be a finite rate > 0, got {self.fixed_hz}"
            )
        if self.max_rate_hz is not None and not (
            math.isfinite(self.max_rate_hz) and self.max_rate_hz > 0
        ):
            raise InvalidQosInput(
                f"{where}: max_rate_hz must be a finite rate > 0 Hz, got {self.max_rate_hz}"
            )


class TopicQos(msgspec.Struct, frozen=True, kw_only=True):
    """The optimum for one topic."""

    robot: str
    topic: str
    rate_hz: float
    deadline_s: float
    depth: int
    #: the effective weight w_i (priority x change factor)
    weight: float
    #: "floor" (at its lowest rate), "ceiling" (at Rmax or the sensor's limit) or "share"
    bound: str
    #: False for a topic with ``fixed_hz`` (counted, not assigned)
    assigned: bool = True


class TopicSolution(msgspec.Struct, frozen=True, kw_only=True):
    """The optimum of the per-topic problem as one method found it."""

    topics: tuple[TopicQos, ...]
    #: C of the capacity constraint, and what the optimum uses of it (sum c_i r_i)
    capacity_hz: float
    used_hz: float
    #: rate per unit of weight of the topics that share the budget (lambda); None when the
    #: budget does not bind (every topic at its ceiling)
    multiplier: float | None
    robots: int
    t_avg: float
    method: str
    solve_time_s: float

    def rate(self, robot: str, topic: str) -> float:
        for t in self.topics:
            if t.robot == robot and t.topic == topic:
                return t.rate_hz
        raise KeyError(f"{robot}/{topic}")


def change_factor(demand: TopicDemand, rmax_hz: float) -> float:
    """sqrt(change_hz), or sqrt(Rmax) when the change rate is not known."""
    return math.sqrt(demand.change_hz if demand.change_hz is not None else rmax_hz)


def effective_weight(demand: TopicDemand, rmax_hz: float) -> float:
    """w_i = priority_i * sqrt(change_hz_i)."""
    return demand.weight * change_factor(demand, rmax_hz)


class _Prepared(msgspec.Struct, frozen=True):
    weights: list[Fraction]
    costs: list[Fraction]
    lows: list[Fraction]
    highs: list[Fraction]
    capacity: Fraction
    robots: int


def _prepare(limits: QosLimits, demands: Sequence[TopicDemand]) -> _Prepared:
    """Check the inputs, compute w, c, the bounds and C; raise when infeasible."""
    if len(demands) == 0:
        raise InvalidQosInput("no topics: give at least one robot with one topic")
    seen: set[tuple[str, str]] = set()
    for d in demands:
        if (d.robot, d.topic) in seen:
            raise InvalidQosInput(f"topic {d.topic!r} of robot {d.robot!r} is listed twice")
        seen.add((d.robot, d.topic))
    rmax, rmin = Fraction(limits.rmax_hz), Fraction(limits.rmin_hz)
    robots = len({d.robot for d in demands})
    capacity = robots * rmax - len(demands) * rmin
    # (5) with d_i >= Dmin needs r_i >= 2 Dmin Rmax / Dmax (less _DEPTH_TOL's sample, as
    # ``_best_depth`` forgives it); Rmin applies too
    floor = max(rmin, 2 * limits.dmin * rmax / limits.dmax - rmax / (limits.dmax * 10**6))
    lows, highs = [], []
    for d in demands:
        if d.fixed_hz is not None:  # not ours to set: its rate is both bounds
            lows.append(Fraction(d.fixed_hz))
            highs.append(Fraction(d.fixed_hz))
            continue
        high = rmax if d.max_rate_hz is None else min(rmax, Fraction(d.max_rate_hz))
        if high < floor:
            raise InfeasibleQosError(
                f"infeasible: topic {d.topic!r} of robot {d.robot!r} can be read at most at "
                f"{float(high):g} Hz, below the lowest rate a topic may get, {float(floor):g} Hz "
                "(Rmin, and 2 Dmin Rmax/Dmax for constraint (5)): raise its max_rate_hz or lower "
                "rmin_hz",
                constraint="r_i <= max_rate_i",
                lhs=float(high),
                rhs=float(floor),
                suggestions=(),
            )
        lows.append(floor)
        highs.append(high)
    costs = [Fraction(d.cost) for d in demands]
    need = sum(c * lo for c, lo in zip(costs, lows, strict=True))
    if need > capacity:
        raise InfeasibleQosError(
            f"infeasible: constraint {CAPACITY} cannot hold with every topic at its lowest rate "
            f"{float(floor):g} Hz: the {len(demands)} topics of {robots} robots need "
            f"{float(need):.6g} samples/s, the capacity is {robots} x {float(rmax):g} - "
            f"{len(demands)} x {float(rmin):g} = {float(capacity):.6g}: raise rmax_hz, lower "
            "rmin_hz (or dmin), or use fewer topics",
            constraint=CAPACITY,
            lhs=float(need),
            rhs=float(capacity),
            suggestions=(),
        )
    weights = [Fraction(effective_weight(d, limits.rmax_hz)) for d in demands]
    return _Prepared(weights, costs, lows, highs, capacity, robots)


def _rates_at(p: _Prepared, lam: Fraction) -> list[Fraction]:
    return [
        min(hi, max(lo, lam * w / c))
        for w, c, lo, hi in zip(p.weights, p.costs, p.lows, p.highs, strict=True)
    ]


def _spent(p: _Prepared, rates: Sequence[Fraction]) -> Fraction:
    return sum((c * r for c, r in zip(p.costs, rates, strict=True)), Fraction(0))


def _water_fill(p: _Prepared) -> tuple[list[Fraction], Fraction | None]:
    """The KKT point: r_i = clamp(lambda w_i/c_i, lo_i, hi_i), sum c_i r_i = C (or all at hi).

    g(lambda) = sum c_i r_i(lambda) is piecewise linear and nondecreasing, with breakpoints where
    a topic leaves its floor (lo c / w) or reaches its ceiling (hi c / w). Find the last
    breakpoint where g <= C by bisection, then solve the linear piece after it exactly.
    """
    if _spent(p, p.highs) <= p.capacity:
        return list(p.highs), None
    points = sorted(
        {lo * c / w for w, c, lo in zip(p.weights, p.costs, p.lows, strict=True)}
        | {hi * c / w for w, c, hi in zip(p.weights, p.costs, p.highs, strict=True)}
    )
    low, high = 0, len(points) - 1  # g(points[0]) <= C (feasible), g(points[-1]) > C
    while high - low > 1:
        mid = (low + high) // 2
        if _spent(p, _rates_at(p, points[mid])) <= p.capacity:
            low = mid
        else:
            high = mid
    left, right = points[low], points[high]
    fixed, free_weight = Fraction(0), Fraction(0)
    for w, c, lo, hi in zip(p.weights, p.costs, p.lows, p.highs, strict=True):
        if lo * c / w <= left and hi * c / w >= right:
            free_weight += w  # strictly inside its bounds on (left, right)
        else:
            fixed += c * min(hi, max(lo, left * w / c))
    lam = (p.capacity - fixed) / free_weight
    return _rates_at(p, lam), lam


def _bound(rate: Fraction, lo: Fraction, hi: Fraction) -> str:
    if rate >= hi:
        return AT_CEILING
    return AT_FLOOR if rate <= lo else SHARE


def _solution(
    limits: QosLimits,
    demands: Sequence[TopicDemand],
    p: _Prepared,
    rates: Sequence[Fraction],
    depths: Sequence[int],
    lam: float | None,
    method: str,
    elapsed_s: float,
) -> TopicSolution:
    topics = tuple(
        TopicQos(
            robot=d.robot,
            topic=d.topic,
            rate_hz=float(r),
            deadline_s=float(1 / r),
            depth=depth,
            weight=float(w),
            bound=FIXED if d.fixed_hz is not None else _bound(r, lo, hi),
            assigned=d.fixed_hz is None,
        )
        for d, r, depth, w, lo, hi in zip(
            demands, rates, depths, p.weights, p.lows, p.highs, strict=True
        )
    )
    return TopicSolution(
        topics=topics,
        capacity_hz=float(p.capacity),
        used_hz=float(_spent(p, rates)),
        multiplier=lam,
        robots=p.robots,
        t_avg=len(demands) / p.robots,
        method=method,
        solve_time_s=elapsed_s,
    )


def solve_topics_closed(limits: QosLimits, demands: Sequence[TopicDemand]) -> TopicSolution:
    """The per-topic problem by exact water-filling (rational arithmetic)."""
    start = time.perf_counter()
    p = _prepare(limits, demands)
    rates, lam = _water_fill(p)
    rmax = Fraction(limits.rmax_hz)
    depths = [_best_depth(rmax, limits.dmax, limits.dmin, r) for r in rates]
    elapsed_s = time.perf_counter() - start
    return _solution(
        limits, demands, p, rates, depths, None if lam is None else float(lam), "closed", elapsed_s
    )


def solve_topics_cvxpy(
    limits: QosLimits, demands: Sequence[TopicDemand], *, solver: str = "CLARABEL"
) -> TopicSolution:
    """The per-topic problem in CVXPY: max sum w log r (exponential cone, CLARABEL), then the
    integer depths by a MILP (SCIPY) with the rates fixed. Neither solver prints anything."""
    import cvxpy

    cp: Any = cvxpy  # server-only dependency; its stubs lack log and sum

    start = time.perf_counter()
    p = _prepare(limits, demands)
    n = len(demands)
    # scaled for the solver: weights summing to 1, rates in units of Rmax (same optimum). The
    # objective is flat near its optimum, so the interior-point answer is good to about 1e-6 of
    # Rmax; asking CLARABEL for tighter gaps makes it report "inaccurate", not better rates
    total = float(sum(p.weights))
    w = [float(x) / total for x in p.weights]
    c = [float(x) for x in p.costs]
    scale = limits.rmax_hz
    share: Any = cp.Variable(n, name="r_over_rmax")
    constraints: list[Any] = [
        c @ share <= float(p.capacity) / scale,
        share >= [float(x) / scale for x in p.lows],
        share <= [float(x) / scale for x in p.highs],
    ]
    problem: Any = cp.Problem(cp.Maximize(w @ cp.log(share)), constraints)
    if _solve(problem, solver) not in _SOLVED:
        raise OptimiserError(f"CVXPY ({solver}) could not solve the rates: {problem.status}")
    solved = [
        min(float(hi), max(float(lo), float(v) * scale))
        for v, lo, hi in zip(share.value, p.lows, p.highs, strict=True)
    ]
    depth: Any = cp.Variable(n, integer=True, name="d")
    bound = [limits.dmax * r / limits.rmax_hz - limits.dmin + 1e-6 for r in solved]
    milp: Any = cp.Problem(
        cp.Maximize(cp.sum(depth)),
        [depth <= bound, depth >= limits.dmin, depth <= limits.dmax],
    )
    if _solve(milp, "SCIPY") not in _SOLVED:
        raise OptimiserError(f"CVXPY (SCIPY) could not solve the depths: {milp.status}")
    depths = [round(float(v)) for v in depth.value]
    elapsed_s = time.perf_counter() - start
    rates = [Fraction(r) for r in solved]
    shared = [r * x / y for r, x, y in zip(solved, c, w, strict=True)]
    lam = None if float(_spent(p, p.highs)) <= float(p.capacity) else max(shared)
    return _solution(limits, demands, p, rates, depths, lam, "cvxpy", elapsed_s)


def solve_topics(
    limits: QosLimits, demands: Sequence[TopicDemand], *, method: TopicMethod = "closed"
) -> TopicSolution:
    if method == "closed":
        return solve_topics_closed(limits, demands)
    if method == "cvxpy":
        return solve_topics_cvxpy(limits, demands)
    raise InvalidQosInput(f"method must be one of {', '.join(TOPIC_METHODS)}, got {method!r}")
