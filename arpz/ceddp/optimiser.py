"""QoS balancing optimiser of seed 001 (section 2.4, eq. 1-6), plus a loss-aware depth check.

Pure logic: values in, values out, no Zenoh and no Rerun, so the CEDDP can call it from its
control loop and tests can call it with hand-computed numbers. The derivations behind every
formula are in docs/qos-optimiser.md; the comments here only say why a step is done the way it is.

Problem (6) of the paper, for one DEADLINE rate R (Hz) and one KEEP_LAST depth D (samples)
shared by every topic of the fleet::

    max  R, D
    s.t. Rmax / T_avg - R >= Rmin            (4)  rate balance
         Dmax * R / Rmax - D >= Dmin         (5)  depth balance
         Rmin <= R <= Rmax
         Dmin <= D <= Dmax,  D integer

How the two objectives are combined: lexicographically, R first, then the largest integer D
given that R. This is not an arbitrary pick among trade-offs: the only constraint that couples
the two variables, (5), loosens as R grows, so raising R never lowers the best D. The "utopia"
point (best R, best D for that R) is therefore feasible and it is the unique Pareto optimum;
every weighted sum with positive weights lands on it too (``solve_cvxpy(weights=...)`` lets the
tests check exactly that). Lexicographic is the honest name for it and needs no weights to tune.

``solve_closed`` computes the optimum in exact rational arithmetic (the float inputs are taken
at their exact binary value), so D is exactly the largest integer that satisfies (5) with no
epsilon. ``solve_cvxpy`` states the same problem in CVXPY, as the paper does, and solves it in
two stages (an LP for R, then a MILP for D with R held at its optimum).
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from fractions import Fraction
from typing import Any, Final, Literal

import msgspec

from arpz.core.errors import ArpzError
from arpz.core.protocol.qos import QosProfile

#: Fast DDS ``max_samples`` default: the "Dmax = 5000" of seed 001 (its reference 17).
DEFAULT_DMAX: Final = 5000
#: A KEEP_LAST history holds at least one sample.
DEFAULT_DMIN: Final = 1
#: Fast DDS defaults (the rmw of ROS 2 Foxy, which the paper ran): heartbeat period and the
#: delay before the writer answers a NACK. Cyclone DDS uses 100 ms and 100 ms.
FASTDDS_HEARTBEAT_PERIOD_S: Final = 3.0
FASTDDS_NACK_DELAY_S: Final = 0.005
#: Probability, at most, that a sample is still missing after the recovery window.
DEFAULT_RESIDUAL_LOSS: Final = 1e-6

Method = Literal["closed", "cvxpy"]
DepthPolicy = Literal["paper", "loss_aware", "max"]
METHODS: Final[tuple[str, ...]] = ("closed", "cvxpy")
DEPTH_POLICIES: Final[tuple[str, ...]] = ("paper", "loss_aware", "max")

#: Constraint names, in the order of problem (6); used in ``binding`` and in error messages.
RATE_BALANCE: Final = "(4) Rmax/T_avg - R >= Rmin"
DEPTH_BALANCE: Final = "(5) Dmax*R/Rmax - D >= Dmin"
RATE_MIN: Final = "R >= Rmin"
RATE_MAX: Final = "R <= Rmax"
DEPTH_MIN: Final = "D >= Dmin"
DEPTH_MAX: Final = "D <= Dmax"

# A rate constraint counts as binding when its slack is below this fraction of Rmax: the
# closed form is exact, but CVXPY's solvers stop at a feasibility tolerance near 1e-7.
_RATE_BINDING_REL: Final = 1e-6
_SOLVED: Final = ("optimal", "optimal_inaccurate")
#: what CVXPY warns with when its status is "optimal_inaccurate" (accepted: ``_SOLVED``)
_INACCURATE_WARNING: Final = "Solution may be inaccurate"


def _solve(problem: Any, solver: str) -> str:
    """``problem.solve(solver=...)``; its status. An inaccurate optimum is accepted on purpose
    (``_SOLVED``: CLARABEL's answer is good to about 1e-6 of Rmax, and asking for tighter gaps
    only makes it say "inaccurate"), so CVXPY's warning that says so is not let out: run under
    ``-W error`` (the test suite) it raised out of the solve instead of returning the answer
    (a property test found an instance; the rates then agreed to 2.3e-4)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=_INACCURATE_WARNING, category=UserWarning)
        problem.solve(solver=solver)
    return str(problem.status)


# D may exceed the exact bound of (5) by this fraction of a sample. Inputs are binary floats:
# Rmin = Rmax/28 typed in decimal can make Dmax R/Rmax come out as 53.99999999999999 instead
# of 54, and an exact floor would then give one sample less than the user's arithmetic (and
# than CVXPY, whose solvers accept the point within their feasibility tolerance).
_DEPTH_TOL: Final = Fraction(1, 10**6)


class OptimiserError(ArpzError, ValueError):
    """Base of the optimiser's errors; a ValueError so callers that validate input catch it."""


class InvalidQosInput(OptimiserError):
    """An input that has no meaning (a negative rate, Dmin > Dmax, no agents, ...)."""


class Suggestion(msgspec.Struct, frozen=True, kw_only=True):
    """One single-parameter change that makes the problem feasible, all else unchanged.

    ``value`` is already rounded in the safe direction (up for "at least", down for "at most"),
    so applying exactly this value gives a feasible problem.
    """

    parameter: Literal["rmax_hz", "rmin_hz", "dmax", "dmin"]
    bound: Literal["at least", "at most"]
    value: float


class InfeasibleQosError(OptimiserError):
    """Problem (6) has no solution; says which bound fails, by how much, and how to fix it.

    ``constraint`` is one of the constraint names of this module; ``lhs`` < ``rhs`` is the
    violated inequality evaluated at the best the other constraints allow; ``suggestions`` are
    the smallest single-parameter changes that restore feasibility, each on its own. When no
    single change can (Dmax below about 2 Dmin T_avg while the rate bound fails too),
    ``suggestions`` is empty and ``together`` holds changes to apply all at once.
    """

    def __init__(
        self,
        message: str,
        *,
        constraint: str,
        lhs: float,
        rhs: float,
        suggestions: tuple[Suggestion, ...],
        together: tuple[Suggestion, ...] = (),
    ) -> None:
        super().__init__(message)
        self.constraint = constraint
        self.lhs = lhs
        self.rhs = rhs
        self.suggestions = suggestions
        self.together = together


def _check_rate(name: str, value: float) -> None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise InvalidQosInput(f"{name} must be a number in Hz, got {value!r}")
    if not math.isfinite(value) or value <= 0:
        raise InvalidQosInput(f"{name} must be a finite rate > 0 Hz, got {value!r}")


def _check_depth(name: str, value: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int):
        raise InvalidQosInput(f"{name} must be an integer number of samples, got {value!r}")
    if value < 1:
        raise InvalidQosInput(f"{name} must be >= 1 sample, got {value!r}")


class QosLimits(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """The bounds of problem (6); loads unchanged from a ``[qos]`` TOML table."""

    rmax_hz: float
    rmin_hz: float
    dmax: int = DEFAULT_DMAX
    dmin: int = DEFAULT_DMIN

    def __post_init__(self) -> None:
        _check_rate("rmax_hz", self.rmax_hz)
        _check_rate("rmin_hz", self.rmin_hz)
        _check_depth("dmax", self.dmax)
        _check_depth("dmin", self.dmin)
        if self.rmin_hz > self.rmax_hz:
            raise InvalidQosInput(
                f"rmin_hz = {self.rmin_hz:g} Hz is above rmax_hz = {self.rmax_hz:g} Hz: "
                "the minimum rate cannot exceed the maximum"
            )
        if self.dmin > self.dmax:
            raise InvalidQosInput(
                f"dmin = {self.dmin} is above dmax = {self.dmax}: "
                "the minimum depth cannot exceed the maximum"
            )


class LinkQuality(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """What the loss-aware depth needs to know about a robot's link and reliable channel."""

    rtt_s: float
    loss_pct: float
    heartbeat_period_s: float = FASTDDS_HEARTBEAT_PERIOD_S
    nack_delay_s: float = FASTDDS_NACK_DELAY_S
    residual_loss: float = DEFAULT_RESIDUAL_LOSS
    #: mean length of a run of lost samples (measured: samples recovered per NACK); a burst of
    #: b samples lost together must all still be held when their recovery starts: + b samples
    burst_samples: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.burst_samples) and self.burst_samples >= 0):
            raise InvalidQosInput(f"burst_samples must be >= 0, got {self.burst_samples!r}")
        for name, value in (
            ("rtt_s", self.rtt_s),
            ("heartbeat_period_s", self.heartbeat_period_s),
            ("nack_delay_s", self.nack_delay_s),
        ):
            if not (math.isfinite(value) and value >= 0):
                raise InvalidQosInput(f"{name} must be a finite time >= 0 s, got {value!r}")
        if not (math.isfinite(self.loss_pct) and 0 <= self.loss_pct < 100):
            raise InvalidQosInput(
                f"loss_pct must be in [0, 100) %, got {self.loss_pct!r}: "
                "at 100 % loss nothing is ever recovered"
            )
        if not (0 < self.residual_loss < 1):
            raise InvalidQosInput(f"residual_loss must be in (0, 1), got {self.residual_loss!r}")
        if self.loss_pct > 0 and self.heartbeat_period_s + self.nack_delay_s + self.rtt_s <= 0:
            raise InvalidQosInput(
                "a lossy link needs a recovery round longer than 0 s: "
                "set rtt_s, heartbeat_period_s or nack_delay_s"
            )


class Constraint(msgspec.Struct, frozen=True, kw_only=True):
    """One constraint of (6) at the optimum.

    ``slack`` is lhs - rhs written as ``... >= 0``. ``binding``: the constraint stops the
    optimum from moving, i.e. R constraints have zero slack (to solver tolerance) and D
    constraints leave less than one sample of room, because D is an integer.
    """

    name: str
    slack: float
    binding: bool


class QosSolution(msgspec.Struct, frozen=True, kw_only=True):
    """The optimum of problem (6) as one method found it."""

    rate_hz: float
    deadline_s: float
    depth: int
    t_avg: float
    binding: tuple[str, ...]
    constraints: tuple[Constraint, ...]
    method: str
    solve_time_s: float


class LossAwareDepth(msgspec.Struct, frozen=True, kw_only=True):
    """KEEP_LAST depth that keeps a sample until it could have been recovered k times.

    ``rounds`` recovery rounds of ``round_s`` each (heartbeat period + NACK delay + round trip)
    bring the probability that a sample is still missing to ``residual_loss``; the history
    must hold a sample for ``hold_s`` = rounds * round_s, i.e. ceil(rate * hold_s) samples.
    """

    depth: int
    rounds: int
    round_s: float
    hold_s: float
    residual_loss: float
    rate_hz: float


class QosAssignment(msgspec.Struct, frozen=True, kw_only=True):
    """What the CEDDP tells every robot to apply: publish at ``rate_hz``, deadline
    ``deadline_s``, writer depth ``depth``.

    ``paper_depth`` is the D of problem (6); ``depth`` differs from it only under the
    "loss_aware" and "max" policies. ``loss_safe`` says whether ``depth`` covers the loss-aware
    depth (None when no link was given); ``paper_loss_safe`` says the same of ``paper_depth``.
    """

    rate_hz: float
    deadline_s: float
    depth: int
    paper_depth: int
    depth_policy: str
    t_avg: float
    topics_per_agent: dict[str, int]
    binding: tuple[str, ...]
    constraints: tuple[Constraint, ...]
    loss: LossAwareDepth | None
    loss_safe: bool | None
    paper_loss_safe: bool | None
    method: str
    solve_time_s: float


def average_topics(topic_counts: Sequence[int]) -> Fraction:
    """T_avg of eq. (2), exact, after checking each T_a of eq. (1) is a positive integer."""
    if isinstance(topic_counts, str | bytes) or len(topic_counts) == 0:
        raise InvalidQosInput("the topic list is empty: give at least one agent's topic count T_a")
    for index, count in enumerate(topic_counts):
        if isinstance(count, bool) or not isinstance(count, int) or count < 1:
            raise InvalidQosInput(
                f"T_a of agent {index} must be an integer >= 1 (its sensor topics plus the "
                f"topics it receives), got {count!r}"
            )
    return Fraction(sum(topic_counts), len(topic_counts))


def _fmt(value: float) -> str:
    return f"{value:.4g}" if abs(value) < 1e4 else f"{value:.0f}"


def _safe_float(
    exact: Fraction, bound: Literal["at least", "at most"], ok: Callable[[Fraction], bool]
) -> float:
    """Round a threshold for display (3 significant digits, whole numbers from 100 up) in the
    direction that keeps it feasible, then step one ulp at a time if the float conversion
    crossed the threshold. Feasibility is monotone in Rmax and Rmin, so rounding away from the
    threshold never breaks it."""
    magnitude = math.floor(math.log10(exact)) if exact > 0 else 0
    decimals = max(0, 2 - magnitude)
    scaled = exact * 10**decimals
    rounded = math.ceil(scaled) if bound == "at least" else math.floor(scaled)
    value = float(Fraction(rounded, 10**decimals))
    if value <= 0:  # rounding down a tiny positive threshold: fall back to the float itself
        value = float(exact)
    toward = math.inf if bound == "at least" else 0.0
    for _ in range(64):
        if ok(Fraction(value)):
            return value
        value = math.nextafter(value, toward)
    raise AssertionError(f"no feasible float near {float(exact)!r}")  # pragma: no cover


def _best_depth(rmax: Fraction, dmax: int, dmin: int, rate: Fraction) -> int:
    """Largest integer D under (5) and D <= Dmax, forgiving _DEPTH_TOL of a sample."""
    return math.floor(min(Fraction(dmax), dmax * rate / rmax - dmin + _DEPTH_TOL))


def _feasible(rmax: Fraction, rmin: Fraction, dmax: int, dmin: int, t_avg: Fraction) -> bool:
    rate = min(rmax, rmax / t_avg - rmin)
    return rate >= rmin and _best_depth(rmax, dmax, dmin, rate) >= dmin


def _suggestion_text(s: Suggestion) -> str:
    verb = "raise" if s.bound == "at least" else "lower"
    label = {"rmax_hz": "Rmax", "rmin_hz": "Rmin", "dmax": "Dmax", "dmin": "Dmin"}[s.parameter]
    if s.parameter.endswith("_hz"):
        return f"{verb} {label} to {s.bound} {s.value:g} Hz"
    return f"{verb} {label} to {s.bound} {int(s.value)} samples"


def _suggestions(limits: QosLimits, t_avg: Fraction) -> tuple[Suggestion, ...]:
    """The smallest change of each single parameter that makes the WHOLE problem feasible.

    Feasible iff Rmax/T_avg >= 2 Rmin (eq. 4 with R >= Rmin) and Dmax R*/Rmax >= 2 Dmin
    (eq. 5 with D >= Dmin, Dmin an integer) where R* = Rmax/T_avg - Rmin; each threshold below
    solves those two inequalities for one parameter. A parameter that cannot fix the problem
    on its own (e.g. Dmax while the rate bound fails) gets no suggestion.
    """
    rmax, rmin = Fraction(limits.rmax_hz), Fraction(limits.rmin_hz)
    dmax, dmin = limits.dmax, limits.dmin
    rate = rmax / t_avg - rmin
    need = 2 * dmin - _DEPTH_TOL  # what Dmax R/Rmax must reach
    found: list[Suggestion] = []
    # Rmax: both Rmax >= 2 Rmin T_avg and R*/Rmax = 1/T_avg - Rmin/Rmax >= 2 Dmin/Dmax.
    headroom = 1 / t_avg - need / dmax
    if headroom > 0:
        threshold = max(2 * rmin * t_avg, rmin / headroom)
        found.append(
            Suggestion(
                parameter="rmax_hz",
                bound="at least",
                value=_safe_float(
                    threshold, "at least", lambda v: _feasible(v, rmin, dmax, dmin, t_avg)
                ),
            )
        )
    # Rmin: both Rmin <= Rmax/(2 T_avg) and R* = Rmax/T_avg - Rmin >= 2 Dmin Rmax/Dmax.
    threshold = min(rmax / (2 * t_avg), rmax / t_avg - need * rmax / dmax)
    if threshold > 0:
        found.append(
            Suggestion(
                parameter="rmin_hz",
                bound="at most",
                value=_safe_float(
                    threshold, "at most", lambda v: _feasible(rmax, v, dmax, dmin, t_avg)
                ),
            )
        )
    if rate >= rmin:  # the depth knobs only help once the rate bound holds
        found.append(
            Suggestion(
                parameter="dmax", bound="at least", value=float(math.ceil(need * rmax / rate))
            )
        )
        if dmax * rate / rmax + _DEPTH_TOL >= 2:
            found.append(
                Suggestion(
                    parameter="dmin",
                    bound="at most",
                    value=float(math.floor((dmax * rate / rmax + _DEPTH_TOL) / 2)),
                )
            )
    return tuple(found)


def _infeasible(limits: QosLimits, t_avg: Fraction) -> InfeasibleQosError | None:
    """None if (6) is feasible, else the error for the first failing bound (R before D,
    since the best D depends on the best R)."""
    rmax, rmin = Fraction(limits.rmax_hz), Fraction(limits.rmin_hz)
    dmax, dmin = limits.dmax, limits.dmin
    if _feasible(rmax, rmin, dmax, dmin, t_avg):
        return None
    suggestions = _suggestions(limits, t_avg)
    together: tuple[Suggestion, ...] = ()
    if suggestions:
        fixes = " or ".join(_suggestion_text(s) for s in suggestions)
    else:
        # Only when (4) fails and Dmax is too small for (5) at any rate (1/T_avg <= 2 Dmin/Dmax):
        # take Rmin down to its (4) threshold, then Dmax up to what (5) needs at that rate.
        new_rmin = _safe_float(rmax / (2 * t_avg), "at most", lambda v: rmax / t_avg - v >= v)
        new_rate = rmax / t_avg - Fraction(new_rmin)
        together = (
            Suggestion(parameter="rmin_hz", bound="at most", value=new_rmin),
            Suggestion(
                parameter="dmax",
                bound="at least",
                value=float(max(dmax, math.ceil((2 * dmin - _DEPTH_TOL) * rmax / new_rate))),
            ),
        )
        fixes = "no single change helps; " + " and ".join(_suggestion_text(s) for s in together)
    rate = rmax / t_avg - rmin  # (4) solved for R; never above Rmax since T_avg >= 1
    if rate < rmin:
        constraint, lhs, rhs = RATE_BALANCE, rate, rmin
        detail = (
            f"{RATE_MIN}: Rmax/T_avg - Rmin = {_fmt(float(rmax / t_avg))} - {_fmt(float(rmin))} "
            f"= {_fmt(float(rate))} < Rmin = {_fmt(float(rmin))} Hz (T_avg = {_fmt(float(t_avg))})"
        )
    else:
        constraint, lhs, rhs = DEPTH_BALANCE, dmax * rate / rmax - dmin, Fraction(dmin)
        detail = (
            f"{DEPTH_MIN}: at the best rate R = {_fmt(float(rate))} Hz, Dmax*R/Rmax - Dmin = "
            f"{_fmt(float(dmax * rate / rmax))} - {dmin} = {_fmt(float(lhs))} < Dmin = {dmin} "
            "samples"
        )
    return InfeasibleQosError(
        f"infeasible: constraint {constraint} cannot hold with {detail}: {fixes}",
        constraint=constraint,
        lhs=float(lhs),
        rhs=float(rhs),
        suggestions=suggestions,
        together=together,
    )


def _constraints(
    limits: QosLimits, t_avg: Fraction, rate: Fraction, depth: int
) -> tuple[Constraint, ...]:
    """Slacks of (6) at (R, D), in exact arithmetic, and which of them hold the optimum."""
    rmax, rmin = Fraction(limits.rmax_hz), Fraction(limits.rmin_hz)
    dmax, dmin = limits.dmax, limits.dmin
    rate_tol = _RATE_BINDING_REL * rmax
    rate_slacks = {
        RATE_BALANCE: rmax / t_avg - rate - rmin,
        RATE_MIN: rate - rmin,
        RATE_MAX: rmax - rate,
    }
    # D is an integer: a D constraint binds when less than one whole sample of room is left.
    depth_slacks = {
        DEPTH_BALANCE: dmax * rate / rmax - depth - dmin,
        DEPTH_MIN: Fraction(depth - dmin),
        DEPTH_MAX: Fraction(dmax - depth),
    }
    out = [
        Constraint(name=n, slack=float(v), binding=v <= rate_tol) for n, v in rate_slacks.items()
    ]
    out += [
        Constraint(name=n, slack=float(v), binding=v < 1 - _DEPTH_TOL)
        for n, v in depth_slacks.items()
    ]
    order = (RATE_BALANCE, DEPTH_BALANCE, RATE_MIN, RATE_MAX, DEPTH_MIN, DEPTH_MAX)
    return tuple(sorted(out, key=lambda c: order.index(c.name)))


def _solution(
    limits: QosLimits, t_avg: Fraction, rate: Fraction, depth: int, method: str, elapsed_s: float
) -> QosSolution:
    constraints = _constraints(limits, t_avg, rate, depth)
    return QosSolution(
        rate_hz=float(rate),
        deadline_s=float(1 / rate),
        depth=depth,
        t_avg=float(t_avg),
        binding=tuple(c.name for c in constraints if c.binding),
        constraints=constraints,
        method=method,
        solve_time_s=elapsed_s,
    )


def solve_closed(limits: QosLimits, topic_counts: Sequence[int]) -> QosSolution:
    """Problem (6) in closed form: R* = min(Rmax, Rmax/T_avg - Rmin), then
    D* = floor(min(Dmax, Dmax R*/Rmax - Dmin)); feasible iff R* >= Rmin and D* >= Dmin."""
    start = time.perf_counter()
    t_avg = average_topics(topic_counts)
    rmax, rmin = Fraction(limits.rmax_hz), Fraction(limits.rmin_hz)
    rate = min(rmax, rmax / t_avg - rmin)
    depth = _best_depth(rmax, limits.dmax, limits.dmin, rate)
    elapsed_s = time.perf_counter() - start
    if rate < rmin or depth < limits.dmin:
        error = _infeasible(limits, t_avg)
        assert error is not None  # same test as _feasible
        raise error
    return _solution(limits, t_avg, rate, depth, "closed", elapsed_s)


def solve_cvxpy(
    limits: QosLimits,
    topic_counts: Sequence[int],
    *,
    solver: str = "SCIPY",
    weights: tuple[float, float] | None = None,
) -> QosSolution:
    """Problem (6) stated in CVXPY, as the paper solves it.

    Default: lexicographic, an LP for R then a MILP for the integer D with R kept within solver
    tolerance of its optimum. ``weights=(w_R, w_D)`` instead solves the single MILP
    max w_R R + w_D D, to show that any positive weights reach the same point.
    SCIPY (scipy.optimize.milp, HiGHS inside) is the default solver because it prints nothing;
    CVXPY's own HIGHS interface prints a banner on stdout, which would break ``--json``.
    """
    import cvxpy as cp  # server-only dependency: robots import this module without it

    start = time.perf_counter()
    t_avg_exact = average_topics(topic_counts)
    t_avg = float(t_avg_exact)
    rmax, rmin, dmax, dmin = limits.rmax_hz, limits.rmin_hz, limits.dmax, limits.dmin
    # cvxpy ships partial annotations (operators on Variables return bool to mypy): Any.
    rate: Any = cp.Variable(name="R")
    depth: Any = cp.Variable(name="D", integer=True)
    problem_6: list[Any] = [
        rmax / t_avg - rate >= rmin,
        dmax * rate / rmax - depth >= dmin,
        rate >= rmin,
        rate <= rmax,
        depth >= dmin,
        depth <= dmax,
    ]
    if weights is not None:
        w_rate, w_depth = weights
        if not (w_rate > 0 and w_depth > 0):
            raise InvalidQosInput(f"weights must both be > 0, got {weights!r}")
        objective = cp.Maximize(w_rate * rate + w_depth * depth)
    else:
        objective = cp.Maximize(rate)  # stage 1 of the lexicographic order
    problem: Any = cp.Problem(objective, problem_6)
    status = _solve(problem, solver)
    if weights is None and status in _SOLVED:
        # Stage 2: the best D among the points that keep R at its optimum (to a tolerance
        # ten times tighter than the one used to call a rate constraint binding).
        keep_rate = rate >= float(rate.value) - _RATE_BINDING_REL * rmax / 10
        problem = cp.Problem(cp.Maximize(depth), [*problem_6, keep_rate])
        status = _solve(problem, solver)
    elapsed_s = time.perf_counter() - start
    if status not in _SOLVED:
        error = _infeasible(limits, t_avg_exact)
        if error is not None:
            raise error
        raise OptimiserError(f"CVXPY ({solver}) could not solve problem (6): status {status}")
    return _solution(
        limits,
        t_avg_exact,
        Fraction(float(rate.value)),
        round(float(depth.value)),
        "cvxpy",
        elapsed_s,
    )


def solve(
    limits: QosLimits, topic_counts: Sequence[int], *, method: Method = "closed"
) -> QosSolution:
    """Problem (6) by the chosen method; both give the same R (to 1e-6) and the same D."""
    if method == "closed":
        return solve_closed(limits, topic_counts)
    if method == "cvxpy":
        return solve_cvxpy(limits, topic_counts)
    raise InvalidQosInput(f"method must be one of {', '.join(METHODS)}, got {method!r}")


def loss_aware_depth(link: LinkQuality, rate_hz: float) -> LossAwareDepth:
    """Depth so that KEEP_LAST does not overwrite a sample before it could be recovered.

    With per-packet loss p, the first send fails with probability p and each recovery round
    (HEARTBEAT -> ACKNACK -> resend, three packets that must all arrive) fails with
    q = 1 - (1 - p)^3. After k rounds a sample is missing with probability p q^k; k is the
    smallest count with p q^k <= residual_loss. A round takes at most one heartbeat period
    (the sample was sent just after a heartbeat), the NACK delay and one round trip. The
    writer must still hold the sample at the last resend, k rounds after it was written, and a
    writer at R Hz evicts a sample D writes later, after D/R s: D >= R * k * round_s.
    """
    _check_rate("rate_hz", rate_hz)
    p = link.loss_pct / 100.0
    round_s = link.heartbeat_period_s + link.nack_delay_s + link.rtt_s
    if p <= link.residual_loss:
        rounds = 0
        residual = p
    else:
        q = 1.0 - (1.0 - p) ** 3
        rounds = max(0, math.ceil(math.log(link.residual_loss / p) / math.log(q)))
        # log() rounding can land one short or one long; settle on the exact smallest k.
        while rounds > 0 and p * q ** (rounds - 1) <= link.residual_loss:
            rounds -= 1
        while p * q**rounds > link.residual_loss:
            rounds += 1
        residual = p * q**rounds
    hold_s = rounds * round_s
    burst = math.ceil(link.burst_samples) if rounds > 0 else 0
    return LossAwareDepth(
        depth=max(1, math.ceil(rate_hz * hold_s) + burst),
        rounds=rounds,
        round_s=round_s,
        hold_s=hold_s,
        residual_loss=residual,
        rate_hz=rate_hz,
    )


def recovery_heartbeat_s(
    *,
    rtt_s: float,
    loss_pct: float,
    profile_s: float,
    rtts: float,
    min_s: float,
    loss_threshold_pct: float,
) -> float:
    """The writers' heartbeat period for a link: ``profile_s`` on a link that loses less than
    ``loss_threshold_pct`` % (or when ``rtts`` is 0), else ``rtts`` round trips, within
    [``min_s``, ``profile_s``].

    Why a heartbeat period from the round trip: a sample lost at the end of what a writer sent
    (or with the samples after it, in a burst) is revealed only by the next heartbeat, so on a
    lossy link the p99 of recovery is about one heartbeat period plus a round trip (measured in
    benchmarks/RESULTS.md: 0.1 s -> 0.03 s cut wifi-bad's p99 staleness by a third). A period
    shorter than a few round trips would only repeat heartbeats whose ACKNACK is on its way;
    a lossless link needs none beyond the profile's (it costs small messages for nothing)."""
    if rtts <= 0 or loss_pct < loss_threshold_pct:
        return profile_s
    return min(profile_s, max(min_s, rtts * rtt_s))


def channel_link(
    profile: QosProfile,
    *,
    rtt_s: float,
    loss_pct: float,
    burst_samples: float = 0.0,
    residual_loss: float = DEFAULT_RESIDUAL_LOSS,
) -> LinkQuality:
    """The link quality with the recovery timings of the reliable channel in force: arpz's
    heartbeat period and NACK delay (0.1 s and 2 ms by default), not Fast DDS's 3 s and 5 ms,
    which would make the loss-aware depth about 30 times too large."""
    return LinkQuality(
        rtt_s=rtt_s,
        loss_pct=loss_pct,
        heartbeat_period_s=profile.heartbeat_period_s,
        nack_delay_s=profile.nack_delay_s,
        residual_loss=residual_loss,
        burst_samples=burst_samples,
    )


def assign_qos(
    limits: QosLimits,
    topics_per_agent: Mapping[str, int],
    *,
    depth_policy: DepthPolicy = "paper",
    link: LinkQuality | None = None,
    method: Method = "closed",
) -> QosAssignment:
    """The assignment the CEDDP publishes to the fleet (issue 4, live QoS control).

    ``depth_policy``: "paper" applies D of (6); "loss_aware" applies the loss-aware depth
    (clamped to [Dmin, Dmax]); "max" applies the larger of the two, capped at Dmax. The two
    last need ``link``. When even Dmax cannot cover the loss-aware depth, ``loss_safe`` is
    False and the caller should report it rather than pretend.
    """
    if depth_policy not in DEPTH_POLICIES:
        raise InvalidQosInput(
            f"depth_policy must be one of {', '.join(DEPTH_POLICIES)}, got {depth_policy!r}"
        )
    if depth_policy != "paper" and link is None:
        raise InvalidQosInput(
            f"depth_policy {depth_policy!r} needs the link quality "
            "(rtt, loss, heartbeat, NACK delay)"
        )
    names = list(topics_per_agent)
    solution = solve(limits, [topics_per_agent[n] for n in names], method=method)
    loss = None if link is None else loss_aware_depth(link, solution.rate_hz)
    depth = solution.depth
    if loss is not None and depth_policy == "loss_aware":
        depth = min(limits.dmax, max(limits.dmin, loss.depth))
    elif loss is not None and depth_policy == "max":
        depth = min(limits.dmax, max(solution.depth, loss.depth))
    return QosAssignment(
        rate_hz=solution.rate_hz,
        deadline_s=solution.deadline_s,
        depth=depth,
        paper_depth=solution.depth,
        depth_policy=depth_policy,
        t_avg=solution.t_avg,
        topics_per_agent={n: topics_per_agent[n] for n in names},
        binding=solution.binding,
        constraints=solution.constraints,
        loss=loss,
        loss_safe=None if loss is None else depth >= loss.depth,
        paper_loss_safe=None if loss is None else solution.depth >= loss.depth,
        method=solution.method,
        solve_time_s=solution.solve_time_s,
    )


def rmax_for_budget(budget_hz: float, topics_per_robot: Mapping[str, int], rmin_hz: float) -> float:
    """The Rmax that makes seed 001's assignment fit ``budget_hz`` samples/s in all.

    Eq. (4) gives every robot R = Rmax/T_avg - Rmin, so the fleet sends about
    N T_avg R = N (Rmax - Rmin T_avg) samples/s; equal to the budget at
    Rmax = budget/N + Rmin T_avg. Never below 2 Rmin T_avg, where R = Rmin: a budget too small
    for every robot's minimum rate leaves them at the minimum (the caller reports it). T counts
    command topics too (eq. 1), so the fleet's sensor rate stays at or below the budget.
    """
    counts = [n for n in topics_per_robot.values() if n > 0]
    if not counts:
        raise InvalidQosInput("no robot with topics to share a budget")
    t_avg = sum(counts) / len(counts)
    return max(budget_hz / len(counts) + rmin_hz * t_avg, 2 * rmin_hz * t_avg)
