"""What every solver returns: one type, so the CLI, the checker and the benchmark treat the
greedy, the exact MILP and the improved heuristic alike."""

from __future__ import annotations

from typing import Literal

import msgspec

from arpz.configure.problem import Problem

Status = Literal["optimal", "time_limit", "feasible", "infeasible", "error"]


class Placement(msgspec.Struct, frozen=True, kw_only=True):
    computer: str
    cpu: float
    performance: float
    #: the chosen setting's parameter value (particles, Hz, ...), expected message frequency and
    #: bandwidth sent, where the model gives them (interpolated along a continuum)
    parameter: float | None = None
    frequency_hz: float | None = None
    bandwidth: float | None = None


class Solution(msgspec.Struct, frozen=True, kw_only=True):
    problem: int
    method: str
    #: optimal (proved), time_limit (best found when the limit hit), feasible (a heuristic's
    #: answer), infeasible (no allocation found; proved so only for the exact method), error
    status: Status
    #: Problem 1: sum of weight x performance. Problem 2: total server capacity. None if no answer.
    objective: float | None
    assignment: dict[str, Placement]
    #: Problem 2: the capacity each server needs (its load). Empty for Problem 1.
    server_capacity: dict[str, float] = msgspec.field(default_factory=dict)
    solve_time_s: float = 0.0
    #: relative MIP gap reported by the exact method (0 when proved optimal)
    gap: float | None = None
    #: best bound on the objective known to the exact method
    bound: float | None = None
    message: str = ""


def build_solution(
    problem: Problem,
    method: str,
    status: Status,
    computer: list[int],
    level: list[int],
    *,
    solve_time_s: float,
    gap: float | None = None,
    bound: float | None = None,
    message: str = "",
) -> Solution:
    """Turn per-node (computer index, setting level) into a Solution with its objective."""
    assignment: dict[str, Placement] = {}
    load = [0.0] * len(problem.computers)
    objective = 0.0
    for n, name in enumerate(problem.nodes):
        cpu, perf = problem.options[n][level[n]]
        detail = problem.details[n][level[n]]
        c = computer[n]
        assignment[name] = Placement(
            computer=problem.computers[c],
            cpu=cpu,
            performance=perf,
            parameter=detail.parameter,
            frequency_hz=detail.frequency_hz,
            bandwidth=detail.bandwidth,
        )
        load[c] += cpu
        objective += problem.weight[n] * perf
    server_capacity: dict[str, float] = {}
    if problem.kind == 2:
        server_capacity = {
            problem.computers[c]: load[c]
            for c in range(len(problem.computers))
            if problem.is_server[c]
        }
        objective = sum(server_capacity.values())
    return Solution(
        problem=problem.kind,
        method=method,
        status=status,
        objective=objective,
        assignment=assignment,
        server_capacity=server_capacity,
        solve_time_s=solve_time_s,
        gap=gap,
        bound=bound,
        message=message,
    )


def no_solution(
    problem: Problem, method: str, status: Status, message: str, *, solve_time_s: float
) -> Solution:
    return Solution(
        problem=problem.kind,
        method=method,
        status=status,
        objective=None,
        assignment={},
        solve_time_s=solve_time_s,
        message=message,
    )
