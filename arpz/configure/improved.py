"""A heuristic that keeps the greedy's speed and fixes its weaknesses.

The greedy of the paper upgrades nodes by their *current* gradient, so a convex curve (the
paper's AMCL, whose gain per CPU grows with CPU) is starved, and once placed a node rarely moves.
Here the placement is searched and the settings are solved exactly for each placement:

* the settings on one computer are a multiple-choice knapsack over integer CPU, solved by
  dynamic programming, so convex and concave curves are treated alike;
* a local search moves one coresidence unit to any allowed computer, or swaps two units, and
  keeps any change that raises the objective (Problem 1) or lowers the server capacity needed
  (Problem 2) without breaking a link; it stops at a local optimum or at its time budget.

The start is the greedy's answer, or the greedy's initial allocation when the greedy failed
after it.
"""

from __future__ import annotations

import math
import time

import numpy as np

from arpz.configure import greedy
from arpz.configure.problem import Problem
from arpz.configure.solution import Solution, build_solution, no_solution
from arpz.configure.state import EPS, State

METHOD = "improved"
LOCAL_OPTIMUM = "local optimum: no move or swap improves"
BUDGET_HIT = "time budget hit before a local optimum"
NEG = -1e18


class _Grid:
    """CPU on an integer grid so the knapsack is exact: steps of 1, 0.1 or 0.01 CPU units,
    else CPU rounded up (never overloads a computer, may waste a fraction of a unit)."""

    def __init__(self, problem: Problem) -> None:
        values = [u for opts in problem.options for u, _ in opts]
        total = sum(max(u for u, _ in opts) for opts in problem.options)
        self.scale = 1
        for scale in (1, 10, 100):
            if all(abs(v * scale - round(v * scale)) < 1e-6 for v in values):
                self.scale = scale
                break
        else:
            self.scale = 100
        while self.scale > 1 and total * self.scale > 200_000:
            self.scale //= 10
        self.cpu = [
            np.array([math.ceil(u * self.scale - 1e-6) for u, _ in opts], dtype=np.int64)
            for opts in problem.options
        ]
        self.value = [
            np.array([problem.weight[n] * p for _, p in opts], dtype=float)
            for n, opts in enumerate(problem.options)
        ]
        self.capacity = [math.floor(cap * self.scale + 1e-6) for cap in problem.capacity]


def _add(dp: np.ndarray, cpu: np.ndarray, value: np.ndarray) -> np.ndarray:
    """Knapsack step: dp over capacity -> dp with one more node that must take one setting."""
    out = np.full_like(dp, NEG)
    size = len(dp)
    for u, v in zip(cpu.tolist(), value.tolist(), strict=True):
        if u >= size:
            continue
        np.maximum(out[u:], dp[: size - u] + v, out=out[u:])
    return out


class _Search:
    def __init__(self, problem: Problem, state: State) -> None:
        self.p = problem
        self.state = state
        self.grid = _Grid(problem) if problem.kind == 1 else None
        self.members: list[list[int]] = [[] for _ in problem.computers]
        for u in range(len(problem.units)):
            self.members[state.computer[problem.units[u][0]]].append(u)
        self.cache: dict[tuple[int, tuple[int, ...]], float] = {}
        self.tables: dict[tuple[int, tuple[int, ...]], np.ndarray] = {}

    # value of a set of units on a computer ------------------------------------------------
    def base(self, c: int) -> np.ndarray:
        assert self.grid is not None
        dp = np.zeros(self.grid.capacity[c] + 1)
        return dp

    def table(self, c: int, units: list[int]) -> np.ndarray:
        """Knapsack table of a set of units on c, built from a cached table of the same set
        less one unit when there is one (a move or swap then costs one knapsack step)."""
        assert self.grid is not None
        key = (c, tuple(sorted(units)))
        hit = self.tables.get(key)
        if hit is not None:
            return hit
        table: np.ndarray | None = None
        for i, u in enumerate(key[1]):
            smaller = self.tables.get((c, key[1][:i] + key[1][i + 1 :]))
            if smaller is not None:
                table = self._add_unit(smaller, u)
                break
        if table is None:
            table = self.base(c)
            for u in key[1]:
                table = self._add_unit(table, u)
        if len(self.tables) > 20_000:
            self.tables.clear()
        self.tables[key] = table
        return table

    def _add_unit(self, table: np.ndarray, u: int) -> np.ndarray:
        assert self.grid is not None
        for n in self.p.units[u]:
            table = _add(table, self.grid.cpu[n], self.grid.value[n])
        return table

    def value(self, c: int, units: list[int]) -> float:
        key = (c, tuple(sorted(units)))
        hit = self.cache.get(key)
        if hit is not None:
            return hit
        if self.p.kind == 2:
            load = sum(self.p.options[n][0][0] for u in units for n in self.p.units[u])
            if self.p.growable(c):
                result = -load
            else:
                result = 0.0 if load <= self.p.capacity[c] + EPS else NEG
        else:
            result = float(self.table(c, units)[-1])
        if len(self.cache) > 200_000:
            self.cache.clear()
        self.cache[key] = result
        return result

    # moves -----------------------------------------------------------------------------------
    def _bandwidth_ok(self, changes: list[tuple[int, int]]) -> bool:
        """Apply unit relocations, test links, undo. ``changes`` = [(unit, new computer)]."""
        st = self.state
        old = [(u, st.computer[self.p.units[u][0]]) for u, _ in changes]
        for u, _ in changes:
            st.remove(u)
        ok = True
        placed: list[int] = []
        for u, c in changes:
            delta = st.traffic(u, c)
            if delta is None or not st.bandwidth_ok(delta):
                ok = False
                break
            st.place(u, c, delta)
            placed.append(u)
        for u in placed:
            st.remove(u)
        for u, c in old:
            st.place(u, c)
        return ok

    def _apply(self, changes: list[tuple[int, int]]) -> None:
        for u, _ in changes:
            src = self.state.computer[self.p.units[u][0]]
            self.members[src].remove(u)
            self.state.remove(u)
        for u, c in changes:
            self.state.place(u, c)
            self.members[c].append(u)

    def run(self, deadline: float) -> bool:
        """Search until no move or swap improves (True) or the deadline (False)."""
        improved = True
        while improved:
            if time.perf_counter() >= deadline:
                return False
            improved = self._move_pass(deadline) or self._swap_pass(deadline)
        return time.perf_counter() < deadline

    def _move_pass(self, deadline: float) -> bool:
        p = self.p
        for u in range(len(p.units)):
            if time.perf_counter() > deadline:
                return False
            c = self.state.computer[p.units[u][0]]
            rest_c = [x for x in self.members[c] if x != u]
            here = self.value(c, self.members[c])
            without = self.value(c, rest_c)
            best_gain, best_d = 1e-9, -1
            for d in p.unit_allowed[u]:
                if d == c:
                    continue
                gain = (
                    without
                    + self.value(d, [*self.members[d], u])
                    - here
                    - self.value(d, self.members[d])
                )
                if gain > best_gain and self._bandwidth_ok([(u, d)]):
                    best_gain, best_d = gain, d
            if best_d >= 0:
                self._apply([(u, best_d)])
                return True
        return False

    def _swap_pass(self, deadline: float) -> bool:
        p = self.p
        n_units = len(p.units)
        for u in range(n_units):
            cu = self.state.computer[p.units[u][0]]
            for v in range(u + 1, n_units):
                if time.perf_counter() > deadline:
                    return False
                cv = self.state.computer[p.units[v][0]]
                if cu == cv or cv not in p.unit_allowed[u] or cu not in p.unit_allowed[v]:
                    continue
                if (
                    p.options[p.units[u][0]] == p.options[p.units[v][0]]
                    and len(p.units[u]) == len(p.units[v]) == 1
                ):
                    continue
                before = self.value(cu, self.members[cu]) + self.value(cv, self.members[cv])
                after_u = [x for x in self.members[cu] if x != u] + [v]
                after_v = [x for x in self.members[cv] if x != v] + [u]
                gain = self.value(cu, after_u) + self.value(cv, after_v) - before
                if gain > 1e-9 and self._bandwidth_ok([(u, cv), (v, cu)]):
                    self._apply([(u, cv), (v, cu)])
                    return True
        return False

    # link repair -----------------------------------------------------------------------------
    def _over(self, link: int, load: float) -> float:
        return max(0.0, load - self.p.link_bandwidth[link])

    def overload(self) -> float:
        return sum(self._over(k, v) for k, v in enumerate(self.state.link_load))

    def repair(self, deadline: float) -> bool:
        """Move units off overloaded links, least overload first, then least value lost.
        True when no link is overloaded any more."""
        p, st = self.p, self.state
        while (current := self.overload()) > EPS:
            if time.perf_counter() > deadline:
                return False
            over = {k for k, v in enumerate(st.link_load) if v > p.link_bandwidth[k] + EPS}
            units: set[int] = set()
            for a, b, _ in p.messages:
                ca, cb = st.computer[a], st.computer[b]
                if ca != cb and p.link_between(ca, cb) in over:
                    units.update((p.unit_of[a], p.unit_of[b]))
            moves: list[tuple[float, int, int]] = []
            for u in sorted(units):
                c = st.computer[p.units[u][0]]
                leave = st.traffic(u, c) or {}
                for d in p.unit_allowed[u]:
                    if d == c or (st.unit_cpu(u) > st.free(d) + EPS and not p.growable(d)):
                        continue
                    arrive = st.traffic(u, d)
                    if arrive is None:
                        continue
                    change = 0.0
                    for k in set(leave) | set(arrive):
                        old = st.link_load[k]
                        new = old - leave.get(k, 0.0) + arrive.get(k, 0.0)
                        change += self._over(k, new) - self._over(k, old)
                    if change < -EPS:
                        moves.append((change, u, d))
            if not moves:
                return False
            moves.sort()
            best_gain, best = float("-inf"), moves[0]
            for change, u, d in moves[:20]:
                if change > moves[0][0] + EPS:
                    break
                c = st.computer[p.units[u][0]]
                gain = (
                    self.value(c, [x for x in self.members[c] if x != u])
                    + self.value(d, [*self.members[d], u])
                    - self.value(c, self.members[c])
                    - self.value(d, self.members[d])
                )
                if gain > best_gain:
                    best_gain, best = gain, (change, u, d)
            _, u, d = best
            self._apply([(u, d)])
            if self.overload() >= current - EPS:
                return False
        return True

    # final settings --------------------------------------------------------------------------
    def levels(self) -> list[int]:
        """Reconstruct the knapsack's choice of setting for every node (Problem 1)."""
        level = [0] * len(self.p.nodes)
        if self.grid is None:
            return level
        grid = self.grid
        for c, units in enumerate(self.members):
            nodes = [n for u in units for n in self.p.units[u]]
            tables = [self.base(c)]
            for n in nodes:
                tables.append(_add(tables[-1], grid.cpu[n], grid.value[n]))
            x = int(np.argmax(tables[-1]))
            for i in range(len(nodes) - 1, -1, -1):
                n = nodes[i]
                target = tables[i + 1][x]
                for k, (u, v) in enumerate(
                    zip(grid.cpu[n].tolist(), grid.value[n].tolist(), strict=True)
                ):
                    if u <= x and abs(tables[i][x - u] + v - target) < 1e-9:
                        level[n] = k
                        x -= u
                        break
        return level


def solve(
    problem: Problem, *, time_budget_s: float = 10.0, seed: list[int] | None = None
) -> Solution:
    """``seed``: a computer per node to start from instead of the greedy's answer (the exact
    method passes its relaxation's placement); links it overloads are repaired first, and the
    greedy's start is used if they cannot be."""
    start = time.perf_counter()
    state = None
    if seed is not None:
        state = _seeded(problem, seed)
        if state is not None and not _Search(problem, state).repair(start + time_budget_s / 2):
            state = None
    if state is None:
        state = _start(problem)
    if state is None:
        return no_solution(
            problem,
            METHOD,
            "infeasible",
            "no initial allocation found (capacity, residence or bandwidth)",
            solve_time_s=time.perf_counter() - start,
        )
    for n in range(len(problem.nodes)):  # placement search works at minimum settings
        state.level[n] = 0
    state.load = [0.0] * len(problem.computers)
    for n, c in enumerate(state.computer):
        state.load[c] += state.cpu(n)
    search = _Search(problem, state)
    converged = search.run(start + time_budget_s)
    level = search.levels()
    return build_solution(
        problem,
        METHOD,
        "feasible",
        list(state.computer),
        level,
        solve_time_s=time.perf_counter() - start,
        message=LOCAL_OPTIMUM if converged else BUDGET_HIT,
    )


def _seeded(problem: Problem, seed: list[int]) -> State | None:
    """A state at minimum settings on the seed's computers (links not checked yet)."""
    state = State(problem)
    for u, members in enumerate(problem.units):
        c = seed[members[0]]
        if c not in problem.unit_allowed[u] or any(seed[n] != c for n in members):
            return None
        state.place(u, c, state.traffic(u, c) or {})
    for c in range(len(problem.computers)):
        if state.load[c] > state.capacity[c] + EPS:
            return None
    if any(state.traffic(u, state.computer[m[0]]) is None for u, m in enumerate(problem.units)):
        return None
    return state


def _start(problem: Problem) -> State | None:
    found = greedy.solve(problem)
    if found.objective is not None:
        state = State(problem)
        index = {name: i for i, name in enumerate(problem.computers)}
        for u, members in enumerate(problem.units):
            state.place(u, index[found.assignment[problem.nodes[members[0]]].computer])
        return state
    state = State(problem)
    if greedy.initial_allocation(problem, state):
        return None
    return state
