"""Exact solution of Problems 1 and 2 as mixed-integer linear programs (CVXPY + HiGHS).

Robots of a fleet are interchangeable, and a MILP over "node n at setting k on computer c"
explores every permutation of them. So the model is solved in steps:

1. An aggregated MILP over *types* of coresidence units (units with the same settings, weights
   and allowed computers). Identical computers (same kind, capacity, pinned load and allowed
   types) are modelled by packing patterns: how many computers of the class hold each count
   vector of unit types, worth the best settings a knapsack finds for it, so their permutations
   disappear. Computers with too many patterns (big servers) count units per type and setting
   instead. Messages are left out, so it is a relaxation: its optimum bounds the true one.
2. The counts are turned back into named nodes, putting each unit where its message partners
   already are, then swapping units of one type (which changes no load and no objective) to
   relieve overloaded links. If the independent checker accepts the result it is optimal,
   because it reaches the relaxation's bound.
3. Otherwise the improved heuristic, and a full MILP with link constraints when it is small
   enough, look for the best placement the links carry; the aggregated bound gives the gap.
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
import time
import warnings
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import cvxpy as cp
import numpy as np
import scipy.sparse as sp

from arpz.configure.check import check
from arpz.configure.problem import Problem
from arpz.configure.solution import Solution, Status, build_solution, no_solution

METHOD = "exact"
DEFAULT_TIME_LIMIT_S = 60.0
#: HiGHS stops when the relative gap is below this; tight, so "optimal" means optimal to the
#: second decimal of any objective this module sees.
MIP_REL_GAP = 1e-7


@contextlib.contextmanager
def _quiet_stdout() -> Iterator[None]:
    """HiGHS prints its banner on the C stdout, which would corrupt ``solve --json``."""
    sys.stdout.flush()
    try:
        saved = os.dup(1)
    except OSError:
        yield
        return
    try:
        with open(os.devnull, "wb") as devnull:
            os.dup2(devnull.fileno(), 1)
            try:
                yield
            finally:
                os.dup2(saved, 1)
    finally:
        os.close(saved)


@dataclass
class _Lp:
    """A MILP being assembled as sparse triplets: max/min obj @ x, A_eq x = b, A_ub x <= b."""

    lower: list[float] = field(default_factory=list)
    upper: list[float] = field(default_factory=list)
    integer: list[bool] = field(default_factory=list)
    obj: list[float] = field(default_factory=list)
    eq: list[tuple[dict[int, float], float]] = field(default_factory=list)
    ub: list[tuple[dict[int, float], float]] = field(default_factory=list)

    def var(self, lo: float, hi: float, *, integer: bool, obj: float = 0.0) -> int:
        self.lower.append(lo)
        self.upper.append(hi)
        self.integer.append(integer)
        self.obj.append(obj)
        return len(self.obj) - 1

    def solve(
        self,
        *,
        maximise: bool,
        time_limit_s: float,
        initial: np.ndarray | None = None,
        backend: str = "highs",
    ) -> tuple[Status, np.ndarray | None, float | None, str]:
        """Returns (status, x, bound on obj @ x, message)."""
        if backend == "cvxpy":
            answer = self._solve_cvxpy(maximise=maximise, time_limit_s=time_limit_s)
        else:
            answer = self._solve_highs(
                maximise=maximise, time_limit_s=time_limit_s, initial=initial
            )
        status, x, bound, _ = answer
        if x is not None and not self._satisfies(*self._matrix(), x):
            # seen at a time limit of 0.2 s on a 40-robot model: a "solution" of all zeros that
            # places no unit; a point that breaks the rows is no solution, whatever the status
            return status, None, bound, "time limit hit before a solution that meets the model"
        return answer

    def _matrix(self) -> tuple[sp.csc_matrix, np.ndarray, np.ndarray]:
        data: list[float] = []
        ri: list[int] = []
        ci: list[int] = []
        lower: list[float] = []
        upper: list[float] = []
        for r, (coefs, b) in enumerate(self.eq + self.ub):
            for col, val in coefs.items():
                data.append(val)
                ri.append(r)
                ci.append(col)
            lower.append(b if r < len(self.eq) else -np.inf)
            upper.append(b)
        a = sp.csc_matrix((data, (ri, ci)), shape=(len(lower), len(self.obj)))
        return a, np.array(lower, dtype=float), np.array(upper, dtype=float)

    def _satisfies(
        self, a: sp.csc_matrix, row_lower: np.ndarray, row_upper: np.ndarray, x: np.ndarray
    ) -> bool:
        """``x`` meets every row, column bound and integrality of the model (to 1e-6)."""
        if len(x) != len(self.obj):
            return False
        tol = 1e-6
        activity = a @ x
        rows = np.all(activity >= row_lower - tol * (1 + np.abs(row_lower))) and np.all(
            activity <= row_upper + tol * (1 + np.abs(row_upper))
        )
        lower, upper = np.array(self.lower, dtype=float), np.array(self.upper, dtype=float)
        cols = np.all(x >= lower - tol) and np.all(x <= upper + tol)
        integer = np.array(self.integer, dtype=bool)
        whole = np.all(np.abs(x[integer] - np.round(x[integer])) <= tol)
        return bool(rows and cols and whole)

    def _solve_highs(
        self, *, maximise: bool, time_limit_s: float, initial: np.ndarray | None
    ) -> tuple[Status, np.ndarray | None, float | None, str]:
        """HiGHS through highspy: the same model, plus a starting solution, which CVXPY's
        HiGHS interface cannot pass (its incumbent lets HiGHS prune from the first node)."""
        import highspy as hp

        a, row_lower, row_upper = self._matrix()
        lp = hp.HighsLp()
        lp.num_col_ = len(self.obj)
        lp.num_row_ = len(row_lower)
        lp.col_cost_ = np.array(self.obj, dtype=float)
        lp.col_lower_ = np.array(self.lower, dtype=float)
        lp.col_upper_ = np.array(self.upper, dtype=float)
        lp.row_lower_ = row_lower
        lp.row_upper_ = row_upper
        lp.sense_ = hp.ObjSense.kMaximize if maximise else hp.ObjSense.kMinimize
        lp.a_matrix_.format_ = hp.MatrixFormat.kColwise
        lp.a_matrix_.start_ = a.indptr
        lp.a_matrix_.index_ = a.indices
        lp.a_matrix_.value_ = a.data
        lp.integrality_ = [
            hp.HighsVarType.kInteger if flag else hp.HighsVarType.kContinuous
            for flag in self.integer
        ]
        with _quiet_stdout():
            highs = hp.Highs()  # type: ignore[no-untyped-call]
            highs.setOptionValue("output_flag", False)
            highs.setOptionValue("time_limit", max(time_limit_s, 0.1))
            highs.setOptionValue("mip_rel_gap", MIP_REL_GAP)
            highs.passModel(lp)
            if initial is not None:
                start = hp.HighsSolution()
                start.col_value = [float(v) for v in initial]
                highs.setSolution(start)
            highs.run()
        status = highs.getModelStatus()
        info = highs.getInfo()
        bound: float | None = None
        if np.isfinite(info.mip_dual_bound):
            bound = float(info.mip_dual_bound)
        has_solution = info.primal_solution_status == 2  # kSolutionStatusFeasible
        x = np.array(highs.getSolution().col_value, dtype=float) if has_solution else None
        if status == hp.HighsModelStatus.kOptimal and x is not None:
            return "optimal", x, bound, ""
        if status == hp.HighsModelStatus.kTimeLimit:
            if x is None:
                return "time_limit", None, bound, "time limit hit before any solution was found"
            return "time_limit", x, bound, "time limit hit"
        if status in (hp.HighsModelStatus.kInfeasible, hp.HighsModelStatus.kUnboundedOrInfeasible):
            return "infeasible", None, None, "the MILP is infeasible"
        return "error", None, None, f"HiGHS ended with status {highs.modelStatusToString(status)}"

    def _solve_cvxpy(
        self, *, maximise: bool, time_limit_s: float
    ) -> tuple[Status, np.ndarray | None, float | None, str]:
        n = len(self.obj)
        cols_int = [i for i, flag in enumerate(self.integer) if flag]
        cols_cont = [i for i, flag in enumerate(self.integer) if not flag]
        # CVXPY sets integrality per variable: one integer and one continuous vector, joined
        # back into column order by a permutation matrix.
        parts: list[cp.Expression] = []
        if cols_int:
            parts.append(cp.Variable(len(cols_int), integer=True))
        if cols_cont:
            parts.append(cp.Variable(len(cols_cont)))
        stacked = parts[0] if len(parts) == 1 else cp.hstack(parts)  # type: ignore[attr-defined]
        order = cols_int + cols_cont
        perm = sp.csr_matrix((np.ones(n), (order, list(range(n)))), shape=(n, n))
        x_expr = perm @ stacked
        constraints: list[cp.Constraint] = [
            x_expr >= np.array(self.lower),
            x_expr <= np.array(self.upper),
        ]
        for rows, sense in ((self.eq, "eq"), (self.ub, "ub")):
            if not rows:
                continue
            data: list[float] = []
            ri: list[int] = []
            ci: list[int] = []
            rhs: list[float] = []
            for r, (coefs, b) in enumerate(rows):
                for col, val in coefs.items():
                    data.append(val)
                    ri.append(r)
                    ci.append(col)
                rhs.append(b)
            a = sp.csr_matrix((data, (ri, ci)), shape=(len(rows), n))
            if sense == "eq":
                constraints.append(a @ x_expr == np.array(rhs))
            else:
                constraints.append(a @ x_expr <= np.array(rhs))
        c = np.array(self.obj)
        objective = cp.Maximize(c @ x_expr) if maximise else cp.Minimize(c @ x_expr)
        prob = cp.Problem(objective, constraints)
        try:
            # CVXPY warns "may be inaccurate" on a time limit; the status says it already.
            with _quiet_stdout(), warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)
                prob.solve(  # type: ignore[no-untyped-call]
                    solver=cp.HIGHS,
                    time_limit=max(time_limit_s, 0.1),
                    mip_rel_gap=MIP_REL_GAP,
                    verbose=False,
                )
        except cp.SolverError as exc:
            return "error", None, None, f"HiGHS failed: {exc}"
        status = prob.status
        info: Any = prob.solver_stats.extra_stats if prob.solver_stats else None
        bound: float | None = None
        if info is not None and getattr(info, "mip_dual_bound", None) is not None:
            raw = float(info.mip_dual_bound)
            if np.isfinite(raw):
                bound = -raw if maximise else raw
        if status == cp.OPTIMAL:
            values = np.asarray(x_expr.value, dtype=float)
            return "optimal", values, bound, ""
        if status == cp.USER_LIMIT and x_expr.value is not None:
            return "time_limit", np.asarray(x_expr.value, dtype=float), bound, "time limit hit"
        if status == cp.USER_LIMIT:
            return "time_limit", None, bound, "time limit hit before any solution was found"
        if status in (cp.INFEASIBLE, "infeasible_or_unbounded"):
            return "infeasible", None, None, "the MILP is infeasible"
        return "error", None, None, f"HiGHS ended with status {status}"


def solve(
    problem: Problem,
    *,
    time_limit_s: float = DEFAULT_TIME_LIMIT_S,
    backend: str = "cvxpy",
    warm_start: bool = False,
) -> Solution:
    """Optimal (or time-limited, with its gap) solution.

    ``backend``: "cvxpy" (CVXPY's HiGHS interface) or "highs" (highspy directly, which can also
    start from the improved heuristic's answer with ``warm_start``). On the case study's fleets
    the incumbent slows HiGHS down rather than speeding it up: most of its time goes into
    closing the bound, not into finding solutions, so ``warm_start`` is off by default.
    """
    from arpz.configure import improved  # improved imports greedy, not exact

    start = time.perf_counter()
    deadline = start + time_limit_s
    best_obj: float | None = None
    best_cl: tuple[list[int], list[int]] | None = None

    def heuristic(budget_s: float, seed: list[int] | None = None) -> None:
        nonlocal best_obj, best_cl
        found = improved.solve(problem, time_budget_s=max(budget_s, 0.5), seed=seed)
        if (
            found.objective is not None
            and not check(problem.model, found)
            and (best_obj is None or _better(problem, found.objective, best_obj))
        ):
            best_obj, best_cl = found.objective, _indices(problem, found)

    if warm_start and backend == "highs":
        heuristic(min(time_limit_s / 10, 5.0))
    # Keep time for the heuristic in case the links reject the aggregated MILP's answer.
    reserve = min(time_limit_s / 4, 30.0)
    agg = _aggregated(
        problem,
        max(deadline - reserve - time.perf_counter(), 0.5),
        incumbent=best_cl,
        backend=backend,
    )
    if agg.status in ("infeasible", "error"):
        failed: Status = agg.status
        return no_solution(
            problem, METHOD, failed, agg.message, solve_time_s=time.perf_counter() - start
        )
    if agg.computer is not None and agg.level is not None:
        solution = build_solution(
            problem,
            METHOD,
            agg.status,
            agg.computer,
            agg.level,
            solve_time_s=time.perf_counter() - start,
            bound=agg.bound,
            gap=0.0 if agg.status == "optimal" else _gap(agg.objective, agg.bound),
            message="aggregated MILP",
        )
        feasible = not check(problem.model, solution) and solution.objective is not None
        if feasible and agg.status == "optimal":
            return solution
        if feasible and solution.objective is not None:
            best_obj, best_cl = solution.objective, (agg.computer, agg.level)
    # Messages matter (or the time limit hit). The aggregated bound stays valid; look for the
    # best placement the links carry: the improved heuristic's, or the full MILP's when it is
    # small enough to try.
    bound = agg.bound
    if agg.computer is not None:
        # from the relaxation's placement, its overloaded links repaired
        heuristic((deadline - time.perf_counter()) / 2, seed=agg.computer)
    if best_cl is None or agg.computer is None:
        heuristic(deadline - time.perf_counter() - 0.5)
    full_status: Status = "time_limit"
    remaining = deadline - time.perf_counter()
    if _full_size(problem) <= FULL_MILP_MAX_PAIRS and remaining > 1.0:
        full = _full(problem, remaining)
        if full.status == "infeasible" and best_cl is None:
            return no_solution(
                problem,
                METHOD,
                "infeasible",
                "no placement satisfies the links (proved by the full MILP)",
                solve_time_s=time.perf_counter() - start,
            )
        if full.bound is not None:
            bound = (
                full.bound
                if bound is None
                else (min(bound, full.bound) if problem.kind == 1 else max(bound, full.bound))
            )
        if full.computer is not None and full.level is not None:
            trial = build_solution(
                problem, METHOD, "feasible", full.computer, full.level, solve_time_s=0.0
            )
            if not check(problem.model, trial) and trial.objective is not None:
                if best_obj is None or not _better(problem, best_obj, trial.objective):
                    best_obj, best_cl = trial.objective, (full.computer, full.level)
                full_status = full.status
    elapsed = time.perf_counter() - start
    if best_cl is None:
        return no_solution(
            problem,
            METHOD,
            "time_limit",
            "no placement found that the links can carry",
            solve_time_s=elapsed,
        )
    gap = _gap(best_obj, bound)
    reached = gap is not None and gap <= 10 * MIP_REL_GAP and agg.status == "optimal"
    status: Status = "optimal" if full_status == "optimal" or reached else "time_limit"
    if status == "optimal":
        gap = 0.0
    return build_solution(
        problem,
        METHOD,
        status,
        best_cl[0],
        best_cl[1],
        solve_time_s=elapsed,
        bound=bound,
        gap=gap,
        message="messages constrain the placement: full MILP and improved heuristic",
    )


#: the full MILP gets a (message, computer pair) variable each; beyond this it is not tried
FULL_MILP_MAX_PAIRS = 60_000


def _full_size(problem: Problem) -> int:
    total = 0
    for a, b, _ in problem.messages:
        ua, ub = problem.unit_of[a], problem.unit_of[b]
        if ua != ub:
            total += len(problem.unit_allowed[ua]) * len(problem.unit_allowed[ub])
    return total


def _better(problem: Problem, a: float, b: float) -> bool:
    return a > b + 1e-9 if problem.kind == 1 else a < b - 1e-9


def _indices(problem: Problem, solution: Solution) -> tuple[list[int], list[int]]:
    comp = {name: i for i, name in enumerate(problem.computers)}
    computer: list[int] = []
    level: list[int] = []
    for n, name in enumerate(problem.nodes):
        placement = solution.assignment[name]
        computer.append(comp[placement.computer])
        opts = problem.options[n]
        level.append(
            min(
                range(len(opts)),
                key=lambda k: (
                    abs(opts[k][0] - placement.cpu) + abs(opts[k][1] - placement.performance)
                ),
            )
        )
    return computer, level


def _gap(objective: float | None, bound: float | None) -> float | None:
    if objective is None or bound is None:
        return None
    return abs(bound - objective) / max(abs(objective), 1e-9)


@dataclass
class _Answer:
    status: Status
    computer: list[int] | None = None
    level: list[int] | None = None
    objective: float | None = None
    bound: float | None = None
    message: str = ""


# -- aggregated formulation ------------------------------------------------------------------


def _unit_signature(problem: Problem, u: int) -> tuple[object, ...]:
    members = sorted((problem.weight[n], problem.options[n]) for n in problem.units[u])
    return (tuple(members), problem.unit_allowed[u])


def _canonical_members(problem: Problem, u: int) -> list[int]:
    """Members of unit u in the order of its signature, so types line up member by member."""
    return sorted(problem.units[u], key=lambda n: (problem.weight[n], problem.options[n]))


#: a class of identical computers is modelled by its packing patterns when it has at most this
#: many (else by per-computer counts)
PATTERN_LIMIT = 20_000
#: ... and when its capacity is at most this many grid steps
PATTERN_MAX_STEPS = 5_000


@dataclass
class _PatternClass:
    """Identical computers modelled by how many of them use each packing pattern. A pattern is
    a count of units per type; its value is the best choice of settings for those units, by a
    knapsack over integer CPU, so the computers' permutations disappear from the MILP."""

    computers: list[int]
    types: list[int]
    patterns: list[tuple[int, ...]]
    values: list[float]
    scale: int
    steps: int
    x_vars: list[int] = field(default_factory=list)


def _unit_items(
    problem: Problem, u: int, scale: int, maximise: bool
) -> list[tuple[np.ndarray, np.ndarray]]:
    items = []
    for n in _canonical_members(problem, u):
        opts = problem.options[n]
        cpu = np.array([round(c * scale) for c, _ in opts], dtype=np.int64)
        value = np.array([problem.weight[n] * p if maximise else 0.0 for _, p in opts])
        items.append((cpu, value))
    return items


def _knap_add(table: np.ndarray, cpu: np.ndarray, value: np.ndarray) -> np.ndarray:
    out = np.full_like(table, _NEG)
    size = len(table)
    for u, v in zip(cpu.tolist(), value.tolist(), strict=True):
        if u < size:
            np.maximum(out[u:], table[: size - u] + v, out=out[u:])
    return out


_NEG = -1e18


def _grid_scale(values: list[float]) -> int | None:
    for scale in (1, 10, 100):
        if all(abs(v * scale - round(v * scale)) < 1e-9 for v in values):
            return scale
    return None


def _pattern_class(
    problem: Problem,
    comps: list[int],
    types: list[int],
    type_units: list[list[int]],
    free: float,
    maximise: bool,
) -> _PatternClass | None:
    """Enumerate the packing patterns of a class, or None when it has too many."""
    cpus = [
        c for t in types for n in problem.units[type_units[t][0]] for c, _ in problem.options[n]
    ]
    scale = _grid_scale([*cpus, free])
    if scale is None or free * scale > PATTERN_MAX_STEPS:
        return None
    steps = round(free * scale)
    unit_items = [_unit_items(problem, type_units[t][0], scale, maximise) for t in types]
    bounds = []
    for t, items in zip(types, unit_items, strict=True):
        smallest = sum(int(cpu.min()) for cpu, _ in items)
        fit = len(type_units[t]) if smallest == 0 else steps // smallest
        bounds.append(min(len(type_units[t]), fit))
    if math.prod(b + 1 for b in bounds) > 50 * PATTERN_LIMIT:
        return None  # certainly too many: do not spend time enumerating
    patterns: list[tuple[int, ...]] = []
    values: list[float] = []
    counts = [0] * len(types)

    def walk(i: int, table: np.ndarray) -> bool:
        if i == len(types):
            patterns.append(tuple(counts))
            values.append(float(table[steps]))
            return len(patterns) <= PATTERN_LIMIT
        for n in range(bounds[i] + 1):
            counts[i] = n
            if n > 0:
                for cpu, value in unit_items[i]:
                    table = _knap_add(table, cpu, value)
                if table[steps] < _NEG / 2:
                    break
            if not walk(i + 1, table):
                return False
        counts[i] = 0
        return True

    if not walk(0, np.zeros(steps + 1)):
        return None
    return _PatternClass(comps, types, patterns, values, scale, steps)


def _pattern_levels(
    problem: Problem,
    cls: _PatternClass,
    pattern: tuple[int, ...],
    type_units: list[list[int]],
    maximise: bool,
) -> dict[int, list[list[int]]]:
    """Best settings for one pattern: per type, per member, the list of levels of its units."""
    items: list[tuple[int, int, np.ndarray, np.ndarray]] = []
    for t, count in zip(cls.types, pattern, strict=True):
        unit = _unit_items(problem, type_units[t][0], cls.scale, maximise)
        for _ in range(count):
            for j, (cpu, value) in enumerate(unit):
                items.append((t, j, cpu, value))
    tables = [np.zeros(cls.steps + 1)]
    for _, _, cpu, value in items:
        tables.append(_knap_add(tables[-1], cpu, value))
    x = cls.steps
    chosen: dict[int, list[list[int]]] = {
        t: [[] for _ in _unit_items(problem, type_units[t][0], cls.scale, maximise)]
        for t in cls.types
    }
    for i in range(len(items) - 1, -1, -1):
        t, j, cpu, value = items[i]
        target = tables[i + 1][x]
        for k, (u, v) in enumerate(zip(cpu.tolist(), value.tolist(), strict=True)):
            if u <= x and abs(tables[i][x - u] + v - target) <= 1e-9 * max(1.0, abs(target)):
                chosen[t][j].append(k)
                x -= u
                break
        else:  # pragma: no cover - the table was built from these items
            raise AssertionError("knapsack backtrack failed")
    return chosen


@dataclass
class _Types:
    """Coresidence units grouped into types (same settings, weights and allowed computers).

    A pinned type (one allowed computer, one setting per member) gets no variable: it only adds
    a load to its computer and a constant to the objective."""

    units: list[list[int]]
    allowed: list[tuple[int, ...]]
    pinned: list[bool]
    #: per computer, the load of the pinned types
    fixed_load: list[float]
    #: the pinned types' share of Problem 1's objective
    constant: float
    #: per computer, whether a type with a choice of settings may use only it; such computers
    #: are not pooled with others into a class of identical computers
    confined: list[bool]


#: what makes computers identical: (server, growable, capacity, pinned load, allowed types)
_ClassKey = tuple[bool, bool, float, float, tuple[int, ...]]


@dataclass
class _AggregatedMilp:
    """The aggregated MILP and where its variables are, to read its answer back."""

    lp: _Lp
    #: per type, per computer outside the pattern classes: how many units of the type it holds
    counts: list[dict[int, int]]
    #: per type, per member, per computer, per setting: how many units run the member at that
    #: setting (empty for a member with a single setting)
    settings: list[list[dict[int, dict[int, int]]]]
    patterns: list[_PatternClass]
    #: objective terms with no variable (pinned types; pinned load on Problem 2's servers)
    constant: float


def _aggregated(
    problem: Problem,
    time_limit_s: float,
    *,
    incumbent: tuple[list[int], list[int]] | None = None,
    backend: str = "highs",
) -> _Answer:
    """The relaxation without messages (the module docstring's step 1), turned back into a
    placement of named nodes (step 2)."""
    types = _unit_types(problem)
    overloaded = _pinned_overload(problem, types)
    if overloaded is not None:
        return _Answer("infeasible", message=overloaded)
    milp = _build_milp(problem, types, _pattern_classes(problem, types))
    status, values, bound, message = _solve_milp(
        problem, types, milp, time_limit_s, incumbent=incumbent, backend=backend
    )
    if values is None:  # the dual bound holds whether or not a solution was found
        total = None if bound is None else bound + milp.constant
        return _Answer(status, bound=total, message=message)
    computer, level = _disaggregate(
        problem, types.units, *_decode_counts(problem, types, milp, values)
    )
    objective = _objective(problem, computer, level)
    total_bound = None if bound is None else bound + milp.constant
    if status == "optimal" and total_bound is None:
        total_bound = objective
    return _Answer(status, computer, level, objective, total_bound, message)


def _unit_types(problem: Problem) -> _Types:
    by_signature: dict[tuple[object, ...], list[int]] = defaultdict(list)
    for u in range(len(problem.units)):
        by_signature[_unit_signature(problem, u)].append(u)
    type_units = list(by_signature.values())
    n_comp = len(problem.computers)
    maximise = problem.kind == 1
    types = _Types(
        units=type_units,
        allowed=[],
        pinned=[False] * len(type_units),
        fixed_load=[0.0] * n_comp,
        constant=0.0,
        confined=[False] * n_comp,
    )
    for t, units in enumerate(type_units):
        members = _canonical_members(problem, units[0])
        allowed = problem.unit_allowed[units[0]]
        types.allowed.append(allowed)
        multi = any(len(problem.options[n]) > 1 for n in members)
        if len(allowed) == 1 and not multi:
            types.pinned[t] = True
            for n in members:
                cpu, perf = problem.options[n][0]
                types.fixed_load[allowed[0]] += len(units) * cpu
                types.constant += len(units) * problem.weight[n] * perf if maximise else 0.0
        elif len(allowed) == 1:
            types.confined[allowed[0]] = True
    return types


def _pinned_overload(problem: Problem, types: _Types) -> str | None:
    """Why no placement exists when the pinned nodes alone overload a computer, else None."""
    for c in range(len(problem.computers)):
        if not problem.growable(c) and problem.capacity[c] - types.fixed_load[c] < -1e-9:
            return f"the nodes pinned to {problem.computers[c]} exceed its capacity"
    return None


def _identical_computers(problem: Problem, types: _Types) -> dict[_ClassKey, list[int]]:
    """Classes of computers that no constraint tells apart (same kind, capacity, pinned load
    and allowed types); any permutation inside a class is an equivalent answer."""
    classes: dict[_ClassKey, list[int]] = defaultdict(list)
    for c in range(len(problem.computers)):
        if types.confined[c]:
            continue
        member_of = tuple(
            t for t, allowed in enumerate(types.allowed) if c in allowed and not types.pinned[t]
        )
        key = (
            problem.is_server[c],
            problem.growable(c),
            round(problem.capacity[c], 9) if not problem.growable(c) else 0.0,
            round(types.fixed_load[c], 9),
            member_of,
        )
        classes[key].append(c)
    return classes


def _pattern_classes(problem: Problem, types: _Types) -> list[_PatternClass]:
    """The classes of identical computers small enough to model by packing patterns.

    The others keep per-computer counts with no symmetry-breaking rows: HiGHS detects their
    permutations itself, and ordering them explicitly (by load or by a random signature) was
    slower."""
    maximise = problem.kind == 1
    pattern_classes: list[_PatternClass] = []
    for (_, growable, _, _, members), comps in _identical_computers(problem, types).items():
        if growable or not members:  # Problem 2 servers, or nothing to place
            continue
        free = problem.capacity[comps[0]] - types.fixed_load[comps[0]]
        cls = _pattern_class(problem, comps, list(members), types.units, free, maximise)
        if cls is not None:
            pattern_classes.append(cls)
    return pattern_classes


def _build_milp(
    problem: Problem, types: _Types, pattern_classes: list[_PatternClass]
) -> _AggregatedMilp:
    lp = _Lp()
    load_terms: list[dict[int, float]] = [defaultdict(float) for _ in problem.computers]
    in_pattern = {c for cls in pattern_classes for c in cls.computers}
    counts, settings, count_rows = _add_count_variables(lp, problem, types, in_pattern, load_terms)
    _add_pattern_variables(lp, pattern_classes, count_rows, maximise=problem.kind == 1)
    for t, row in enumerate(count_rows):
        if not types.pinned[t]:
            lp.eq.append((row, float(len(types.units[t]))))
    constant = _add_capacities(lp, problem, types, load_terms)
    return _AggregatedMilp(lp, counts, settings, pattern_classes, constant)


def _add_count_variables(
    lp: _Lp,
    problem: Problem,
    types: _Types,
    in_pattern: set[int],
    load_terms: list[dict[int, float]],
) -> tuple[list[dict[int, int]], list[list[dict[int, dict[int, int]]]], list[dict[int, float]]]:
    """Per type, a count of its units on each allowed computer outside the pattern classes, and
    per member with a choice of settings, how many of them use each setting there. Returns
    (counts, settings, the rows that sum a type's counts, still open for the patterns)."""
    maximise = problem.kind == 1
    counts: list[dict[int, int]] = []
    settings: list[list[dict[int, dict[int, int]]]] = []
    count_rows: list[dict[int, float]] = []
    for t, units in enumerate(types.units):
        members = _canonical_members(problem, units[0])
        if types.pinned[t]:
            counts.append({})
            settings.append([{} for _ in members])
            count_rows.append({})
            continue
        count = len(units)
        g = {c: lp.var(0, count, integer=True) for c in types.allowed[t] if c not in in_pattern}
        counts.append(g)
        count_rows.append({v: 1.0 for v in g.values()})
        per_member: list[dict[int, dict[int, int]]] = []
        for n in members:
            opts = problem.options[n]
            w = problem.weight[n]
            if len(opts) == 1:
                cpu, perf = opts[0]
                for c, gv in g.items():
                    load_terms[c][gv] += cpu
                    if maximise:
                        lp.obj[gv] += w * perf
                per_member.append({})
                continue
            zs: dict[int, dict[int, int]] = {}
            for c, gv in g.items():
                zs[c] = {}
                row: dict[int, float] = {gv: -1.0}
                for k, (cpu, perf) in enumerate(opts):
                    zv = lp.var(0, count, integer=True, obj=w * perf if maximise else 0.0)
                    zs[c][k] = zv
                    row[zv] = 1.0
                    load_terms[c][zv] += cpu
                lp.eq.append((row, 0.0))
            per_member.append(zs)
        settings.append(per_member)
    return counts, settings, count_rows


def _add_pattern_variables(
    lp: _Lp,
    pattern_classes: list[_PatternClass],
    count_rows: list[dict[int, float]],
    *,
    maximise: bool,
) -> None:
    """Per class, how many of its computers use each pattern (all of them use one), and the
    units those patterns hold added to their types' counts."""
    for cls in pattern_classes:
        size = len(cls.computers)
        cls.x_vars = [
            lp.var(0, size, integer=True, obj=value if maximise else 0.0) for value in cls.values
        ]
        lp.eq.append(({v: 1.0 for v in cls.x_vars}, float(size)))
        for i, t in enumerate(cls.types):
            for pattern, xv in zip(cls.patterns, cls.x_vars, strict=True):
                if pattern[i]:
                    count_rows[t][xv] = count_rows[t].get(xv, 0.0) + pattern[i]


def _add_capacities(
    lp: _Lp, problem: Problem, types: _Types, load_terms: list[dict[int, float]]
) -> float:
    """A capacity row per fixed-size computer. Problem 2 minimises the load of the growable
    servers instead; their pinned load joins the objective's constant, which is returned."""
    maximise = problem.kind == 1
    constant = types.constant
    for c in range(len(problem.computers)):
        if problem.growable(c):
            if not maximise:
                for var, coef in load_terms[c].items():
                    lp.obj[var] += coef
                constant += types.fixed_load[c]
            continue
        if load_terms[c]:
            lp.ub.append((dict(load_terms[c]), problem.capacity[c] - types.fixed_load[c]))
    return constant


def _solve_milp(
    problem: Problem,
    types: _Types,
    milp: _AggregatedMilp,
    time_limit_s: float,
    *,
    incumbent: tuple[list[int], list[int]] | None,
    backend: str,
) -> tuple[Status, np.ndarray | None, float | None, str]:
    """(status, values, bound without the constant, message), as ``_Lp.solve``."""
    lp = milp.lp
    if not lp.obj:  # every type pinned: nothing to decide
        return "optimal", np.zeros(0), 0.0, ""
    initial = None
    if incumbent is not None and not milp.patterns:
        # pattern variables have no value to start from in a per-computer placement
        initial = _counts_of(
            problem, incumbent, types.units, milp.counts, milp.settings, len(lp.obj)
        )
    return lp.solve(
        maximise=problem.kind == 1, time_limit_s=time_limit_s, initial=initial, backend=backend
    )


def _decode_counts(
    problem: Problem, types: _Types, milp: _AggregatedMilp, values: np.ndarray
) -> tuple[list[dict[int, int]], list[list[dict[int, list[int]]]]]:
    """The MILP's values as, per type, units per computer, and per member and computer, the
    settings its units there use (a pool of levels, handed out to named units later)."""
    counts = [{c: round(values[v]) for c, v in g.items()} for g in milp.counts]
    levels: list[list[dict[int, list[int]]]] = []
    for per_member in milp.settings:
        member_levels: list[dict[int, list[int]]] = []
        for zs in per_member:
            by_comp: dict[int, list[int]] = {}
            for c, ks in zs.items():
                pool: list[int] = []
                for k, v in ks.items():
                    pool.extend([k] * round(values[v]))
                by_comp[c] = pool
            member_levels.append(by_comp)
        levels.append(member_levels)
    for cls in milp.patterns:
        _decode_patterns(problem, types, cls, values, counts, levels)
    for t in range(len(types.units)):
        if types.pinned[t]:
            counts[t] = {types.allowed[t][0]: len(types.units[t])}
    return counts, levels


def _decode_patterns(
    problem: Problem,
    types: _Types,
    cls: _PatternClass,
    values: np.ndarray,
    counts: list[dict[int, int]],
    levels: list[list[dict[int, list[int]]]],
) -> None:
    """Give each computer of a pattern class one of the patterns chosen, with its best settings."""
    maximise = problem.kind == 1
    free_comps = list(cls.computers)
    for pattern, xv in zip(cls.patterns, cls.x_vars, strict=True):
        for _ in range(round(values[xv])):
            c = free_comps.pop(0)
            chosen = _pattern_levels(problem, cls, pattern, types.units, maximise)
            for i, t in enumerate(cls.types):
                if pattern[i]:
                    counts[t][c] = pattern[i]
                for j, pool in enumerate(chosen[t]):
                    if pool:
                        levels[t][j][c] = pool


def _counts_of(
    problem: Problem,
    incumbent: tuple[list[int], list[int]],
    type_units: list[list[int]],
    g_vars: list[dict[int, int]],
    z_vars: list[list[dict[int, dict[int, int]]]],
    size: int,
) -> np.ndarray:
    """A known allocation as values of the aggregated variables (HiGHS's starting incumbent)."""
    computer, level = incumbent
    x0 = np.zeros(size)
    for t, units in enumerate(type_units):
        for u in units:
            members = _canonical_members(problem, u)
            c = computer[members[0]]
            if c in g_vars[t]:
                x0[g_vars[t][c]] += 1
            for j, n in enumerate(members):
                zs = z_vars[t][j]
                if c in zs:
                    x0[zs[c][level[n]]] += 1
    return x0


def _objective(problem: Problem, computer: list[int], level: list[int]) -> float:
    if problem.kind == 1:
        return sum(problem.weight[n] * problem.options[n][level[n]][1] for n in range(len(level)))
    return sum(
        problem.options[n][level[n]][0] for n in range(len(level)) if problem.is_server[computer[n]]
    )


def _disaggregate(
    problem: Problem,
    type_units: list[list[int]],
    counts: list[dict[int, int]],
    levels: list[list[dict[int, list[int]]]],
) -> tuple[list[int], list[int]]:
    """Give every counted slot to a named unit, near its message partners, then swap units of
    one type to relieve overloaded links."""
    n_nodes = len(problem.nodes)
    computer = [-1] * n_nodes
    level = [0] * n_nodes
    order = sorted(
        range(len(type_units)),
        key=lambda t: (len(problem.unit_allowed[type_units[t][0]]), -len(type_units[t])),
    )
    for t in order:
        units = type_units[t]
        left = dict(counts[t]) if counts[t] else {problem.unit_allowed[units[0]][0]: len(units)}
        for u in units:
            best_c, best_aff = -1, -1.0
            for c, slots in left.items():
                if slots <= 0:
                    continue
                aff = 0.0
                for n in problem.units[u]:
                    for m, bw in problem.partners[n]:
                        if computer[m] == c:
                            aff += bw
                if aff > best_aff:
                    best_c, best_aff = c, aff
            left[best_c] -= 1
            for n in problem.units[u]:
                computer[n] = best_c
        # settings: hand out each member's pooled levels on each computer
        for j, by_comp in enumerate(levels[t]):
            pools = {c: list(pool) for c, pool in by_comp.items()}
            for u in units:
                n = _canonical_members(problem, u)[j]
                pool = pools.get(computer[n])
                level[n] = pool.pop() if pool else 0
    _repair_links(problem, type_units, computer, level)
    return computer, level


def _excess(problem: Problem, computer: list[int]) -> tuple[float, list[float]]:
    load = [0.0] * len(problem.link_bandwidth)
    unlinked = 0.0
    for a, b, bw in problem.messages:
        ca, cb = computer[a], computer[b]
        if ca == cb:
            continue
        link = problem.link_between(ca, cb)
        if link is None:
            unlinked += 1.0 + bw
        else:
            load[link] += bw
    over = sum(max(0.0, load[k] - problem.link_bandwidth[k]) for k in range(len(load)))
    return over + 1e6 * unlinked, load


def _repair_links(
    problem: Problem, type_units: list[list[int]], computer: list[int], level: list[int]
) -> None:
    """Swap two units of one type (with their settings): loads and objective stay the same."""
    excess, _ = _excess(problem, computer)
    if excess <= 1e-9:
        return
    deadline = time.perf_counter() + 5.0
    improved = True
    while improved and excess > 1e-9 and time.perf_counter() < deadline:
        improved = False
        for units in type_units:
            if len(units) < 2:
                continue
            for i, u in enumerate(units):
                for v in units[i + 1 :]:
                    cu, cv = computer[problem.units[u][0]], computer[problem.units[v][0]]
                    if cu == cv:
                        continue
                    _swap(problem, u, v, computer, level)
                    trial, _ = _excess(problem, computer)
                    if trial < excess - 1e-9:
                        excess = trial
                        improved = True
                    else:
                        _swap(problem, u, v, computer, level)
                    if excess <= 1e-9:
                        return


def _swap(problem: Problem, u: int, v: int, computer: list[int], level: list[int]) -> None:
    mu, mv = _canonical_members(problem, u), _canonical_members(problem, v)
    for a, b in zip(mu, mv, strict=True):
        computer[a], computer[b] = computer[b], computer[a]
        level[a], level[b] = level[b], level[a]


# -- full formulation ------------------------------------------------------------------------


def _full(problem: Problem, time_limit_s: float) -> _Answer:
    """Every unit placed by a binary per allowed computer; messages on links that could
    overflow are counted exactly; messages between unlinked computers are forbidden."""
    lp = _Lp()
    maximise = problem.kind == 1
    n_comp = len(problem.computers)
    y: list[dict[int, int]] = []
    for u in range(len(problem.units)):
        yu = {c: lp.var(0, 1, integer=True) for c in problem.unit_allowed[u]}
        y.append(yu)
        lp.eq.append(({v: 1.0 for v in yu.values()}, 1.0))
    load_terms: list[dict[int, float]] = [defaultdict(float) for _ in range(n_comp)]
    s_vars: dict[int, list[int]] = {}
    for n in range(len(problem.nodes)):
        opts = problem.options[n]
        yu = y[problem.unit_of[n]]
        w = problem.weight[n]
        if len(opts) == 1:
            cpu, perf = opts[0]
            for c, v in yu.items():
                load_terms[c][v] += cpu
                if maximise:
                    lp.obj[v] += w * perf
            continue
        s = [lp.var(0, 1, integer=True, obj=w * p if maximise else 0.0) for _, p in opts]
        s_vars[n] = s
        lp.eq.append(({v: 1.0 for v in s}, 1.0))
        umax = max(u for u, _ in opts)
        total: dict[int, float] = {k: -opts[i][0] for i, k in enumerate(s)}
        for c, yv in yu.items():
            vv = lp.var(0, umax, integer=False)
            lp.ub.append(({vv: 1.0, yv: -umax}, 0.0))
            total[vv] = 1.0
            load_terms[c][vv] += 1.0
        lp.eq.append((total, 0.0))
    for c in range(n_comp):
        if problem.growable(c):
            if not maximise:
                for var, coef in load_terms[c].items():
                    lp.obj[var] += coef
            continue
        lp.ub.append((dict(load_terms[c]), problem.capacity[c]))

    # Links: only those the messages could overflow need rows.
    potential = [0.0] * len(problem.link_bandwidth)
    for a, b, bw in problem.messages:
        ua, ub = problem.unit_of[a], problem.unit_of[b]
        if ua == ub:
            continue
        for k, (c, d) in enumerate(problem.link_ends):
            if (c in y[ua] and d in y[ub]) or (d in y[ua] and c in y[ub]):
                potential[k] += bw
    link_rows: dict[int, dict[int, float]] = {}
    for a, b, bw in problem.messages:
        ua, ub = problem.unit_of[a], problem.unit_of[b]
        if ua == ub:
            continue
        for c, yc in y[ua].items():
            for d, yd in y[ub].items():
                if c == d:
                    continue
                link = problem.link_between(c, d)
                if link is None:
                    lp.ub.append(({yc: 1.0, yd: 1.0}, 1.0))
                elif potential[link] > problem.link_bandwidth[link] + 1e-9:
                    q = lp.var(0, 1, integer=False)
                    lp.ub.append(({yc: 1.0, yd: 1.0, q: -1.0}, 1.0))
                    link_rows.setdefault(link, {})[q] = bw
    for link, row in link_rows.items():
        lp.ub.append((row, problem.link_bandwidth[link]))

    status, x, bound, message = lp.solve(maximise=maximise, time_limit_s=time_limit_s)
    if x is None:  # the dual bound holds whether or not a solution was found
        return _Answer(status, bound=bound, message=message)
    computer = [-1] * len(problem.nodes)
    level = [0] * len(problem.nodes)
    for u, yu in enumerate(y):
        c = max(yu, key=lambda c: x[yu[c]])
        for n in problem.units[u]:
            computer[n] = c
    for n, s in s_vars.items():
        level[n] = int(np.argmax([x[v] for v in s]))
    return _Answer(status, computer, level, _objective(problem, computer, level), bound, message)
