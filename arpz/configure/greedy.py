"""The paper's greedy heuristics: Algorithm 1 (with Algorithm 2) for Problem 1, Algorithm 3 for
Problem 2, as faithful as the pseudo-code allows. Where it is vague, the choice made is written
next to the code and collected in docs/configure.md ("Greedy: interpretations"):

* Coresidence groups are placed and moved as one unit (the only way to keep constraint (9)).
* "Computers with largest capacity" is read as largest FREE capacity at the time of placing.
* Every allowed computer is tried for a residence-constrained node (the authors' code tries only
  the first allowed server and aborts on large instances; that bug is not reproduced).
* The bandwidth loop of Algorithm 1 lines 1-6 is a check made at each placement: a computer whose
  links cannot carry the node's messages is skipped; if no computer is left, the greedy fails.
* Algorithm 2's gradient is the weighted gain per CPU unit of the node's next setting,
  w (P_next - P_now) / (U_next - U_now); "R_c.free > 0" is read as "the next setting fits".
* A "full" computer (Algorithm 1, line 9) is one where some node could still be upgraded but its
  next setting does not fit in the free capacity (free == 0 with 1 % steps, as in the paper).
* ``reading="authors"`` (the default) follows the authors' code where the pseudo-code is vague
  (perf_ros, src/tool/greedy_1.py): the gradient of a node is the gain of the step it last took
  (``node.ratio = new_perf - old_perf`` after each 1 % step; before its first step, the gain of
  that step), and Algorithm 1 lines 10-11 move a node that has not reached its maximum only to a
  computer where its MAXIMUM setting fits (``feasible(settings[1], computer_new, ...)``), then
  upgrade it at once. ``reading="literal"`` is the pseudo-code read on its own: the gain of the
  NEXT step, and a move wherever the current setting fits. docs/configure.md compares both.
* Algorithm 3 puts a node on the first computer in C_min (ascending capacity, servers at 0) where
  it fits, and grows a server only when none fits: read literally, the zero-capacity servers that
  head C_min would take every node and the robots would stay empty.
"""

from __future__ import annotations

import time
from typing import Literal

from arpz.configure.problem import Problem
from arpz.configure.solution import Solution, build_solution, no_solution
from arpz.configure.state import EPS, State

METHOD = "greedy"

#: how Algorithm 2's gradient and Algorithm 1's moves are read (module docstring)
Reading = Literal["authors", "literal"]
READINGS: tuple[Reading, ...] = ("authors", "literal")


def solve(problem: Problem, *, reading: Reading = "authors") -> Solution:
    start = time.perf_counter()
    if problem.kind == 1:
        state, failure = _problem1(problem, reading)
    else:
        state, failure = _problem2(problem)
    elapsed = time.perf_counter() - start
    if state is None:
        return no_solution(problem, METHOD, "infeasible", failure, solve_time_s=elapsed)
    return build_solution(
        problem, METHOD, "feasible", state.computer, state.level, solve_time_s=elapsed
    )


# -- Problem 1 -------------------------------------------------------------------------------


def _largest_free(
    state: State, u: int, candidates: list[int]
) -> tuple[int, dict[int, float]] | None:
    best: tuple[int, dict[int, float]] | None = None
    for c in candidates:
        delta = state.can_place(u, c)
        if delta is not None and (best is None or state.free(c) > state.free(best[0]) + EPS):
            best = (c, delta)
    return best


def initial_allocation(problem: Problem, state: State) -> str:
    """Algorithm 1 lines 1-6: minimum settings; residence, then coresidence, then the rest,
    biggest CPU first, each on the allowed computer with the most free capacity. Returns "" on
    success, else why it failed."""
    model_nodes = problem.model.nodes
    resident = [
        u
        for u, members in enumerate(problem.units)
        if any(model_nodes[n].residence is not None for n in members)
    ]
    grouped = [
        u for u, members in enumerate(problem.units) if len(members) > 1 and u not in resident
    ]
    rest = [u for u in range(len(problem.units)) if u not in resident and u not in grouped]
    for batch in (resident, grouped, rest):
        for u in sorted(batch, key=lambda u: -state.unit_cpu(u)):
            choice = _largest_free(state, u, list(problem.unit_allowed[u]))
            if choice is None:
                names = ", ".join(problem.nodes[n] for n in problem.units[u])
                return f"no computer can take {names} at its minimum setting"
            state.place(u, *choice)
    return ""


def _gradient(problem: Problem, state: State, n: int, reading: Reading = "literal") -> float:
    """Weighted performance gain per CPU unit: of the next step (literal), or of the step last
    taken (authors; the first step's before any), -inf when the node is at its maximum."""
    opts = problem.options[n]
    k = state.level[n]
    if k + 1 >= len(opts):
        return float("-inf")
    low = k - 1 if reading == "authors" and k > 0 else k
    du = opts[low + 1][0] - opts[low][0]
    dp = problem.weight[n] * (opts[low + 1][1] - opts[low][1])
    return dp / du if du > EPS else float("inf")


def upgrade_conf_nodes(
    problem: Problem, state: State, configurable: list[int], reading: Reading = "literal"
) -> None:
    """Algorithm 2: raise the best-gradient node one step while its computer has room."""
    pending = [n for n in configurable if state.level[n] + 1 < len(problem.options[n])]
    while pending:
        n = max(pending, key=lambda m: _gradient(problem, state, m, reading))
        opts = problem.options[n]
        k = state.level[n]
        if k + 1 >= len(opts):
            pending.remove(n)
            continue
        c = state.computer[n]
        du = opts[k + 1][0] - opts[k][0]
        if state.free(c) + EPS >= du:
            state.level[n] = k + 1
            state.load[c] += du
        else:
            pending.remove(n)


def _full(problem: Problem, state: State, c: int) -> bool:
    if state.free(c) <= EPS:
        return True
    for n, where in enumerate(state.computer):
        if where != c:
            continue
        opts = problem.options[n]
        k = state.level[n]
        if k + 1 < len(opts) and opts[k + 1][0] - opts[k][0] > state.free(c) + EPS:
            return True
    return False


def _unit_gradient(problem: Problem, state: State, u: int, reading: Reading = "literal") -> float:
    return max(_gradient(problem, state, n, reading) for n in problem.units[u])


def _max_cpu(problem: Problem, u: int) -> float:
    return sum(problem.options[n][-1][0] for n in problem.units[u])


def _relocate(
    problem: Problem, state: State, *, only_upgradable: bool, reading: Reading = "literal"
) -> None:
    """Algorithm 1 lines 9-11 (only_upgradable) and 13-15: move nodes off full computers to the
    non-full computer with the most free capacity that can hold them, best gradient first.

    Lines 10-11 under the authors' reading: the target must hold the unit at its maximum
    settings, and the moved unit is upgraded at once (greedy_1.py's ``gradients_aux``)."""
    authors = only_upgradable and reading == "authors"
    n_comp = len(problem.computers)
    full = [c for c in range(n_comp) if _full(problem, state, c)]
    not_full = [c for c in range(n_comp) if c not in full]
    for c in full:
        here = sorted({problem.unit_of[n] for n, w in enumerate(state.computer) if w == c})
        if only_upgradable:
            here = [u for u in here if _unit_gradient(problem, state, u, reading) > float("-inf")]
        here.sort(key=lambda u: -_unit_gradient(problem, state, u, reading))
        for u in here:
            need = _max_cpu(problem, u) if authors else state.unit_cpu(u)
            targets = [d for d in not_full if d in problem.unit_allowed[u]]
            best = None
            for d in targets:
                if state.free(d) + EPS >= need and (
                    best is None or state.free(d) > state.free(best) + EPS
                ):
                    best = d
            if best is not None and state.move(u, best) and authors:
                moved = [n for n in problem.units[u] if len(problem.options[n]) > 1]
                upgrade_conf_nodes(problem, state, moved, reading)


def _problem1(problem: Problem, reading: Reading = "authors") -> tuple[State | None, str]:
    state = State(problem)
    failure = initial_allocation(problem, state)
    if failure:
        return None, failure
    configurable = [n for n in range(len(problem.nodes)) if len(problem.options[n]) > 1]
    upgrade_conf_nodes(problem, state, configurable, reading)
    _relocate(problem, state, only_upgradable=True, reading=reading)
    upgrade_conf_nodes(problem, state, configurable, reading)
    _relocate(problem, state, only_upgradable=False, reading=reading)
    upgrade_conf_nodes(problem, state, configurable, reading)
    return state, ""


# -- Problem 2 -------------------------------------------------------------------------------


def _problem2(problem: Problem) -> tuple[State | None, str]:
    """Algorithm 3: biggest node first, onto the smallest computer; servers grow when needed."""
    state = State(problem)
    c_min = sorted(range(len(problem.computers)), key=lambda c: state.capacity[c])
    model_nodes = problem.model.nodes
    by_cpu = sorted(range(len(problem.units)), key=lambda u: -state.unit_cpu(u))
    resident = [
        u for u in by_cpu if any(model_nodes[n].residence is not None for n in problem.units[u])
    ]
    rest = [u for u in by_cpu if u not in resident]
    for u in resident + rest:
        placed = False
        for c in c_min:
            delta = state.can_place(u, c)
            if delta is not None:
                state.place(u, c, delta)
                placed = True
                break
        if not placed:
            for c in c_min:
                if not problem.growable(c):
                    continue
                delta = state.can_place(u, c, grow=True)
                if delta is not None:
                    state.place(u, c, delta)
                    placed = True
                    break
        if not placed:
            names = ", ".join(problem.nodes[n] for n in problem.units[u])
            return None, f"no computer can take {names} (capacity, residence or bandwidth)"
    return state, ""
