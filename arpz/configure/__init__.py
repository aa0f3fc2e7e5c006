"""Automatic configuration of node settings and placement (seed 002, Cano et al. 2016).

Pure logic: a model file in, a Solution out; only ``characterise`` talks to a fleet, and only
through ``arpz.core.transport``. ``python -m arpz.configure --help`` lists the commands.
"""

from __future__ import annotations

from typing import Literal

from arpz.configure.check import Loads, check, loads
from arpz.configure.eq10 import Eq10Node, Eq10Summary, summarise
from arpz.configure.model import (
    Computer,
    Continuum,
    Link,
    Message,
    Model,
    ModelError,
    Node,
    Setting,
    SettingDetail,
    decode_model,
    dump_json,
    dump_toml,
    load_model,
    node_details,
    validate,
)
from arpz.configure.problem import Problem
from arpz.configure.regression import (
    Curve,
    FitError,
    ParameterCurves,
    best_fit,
    expand,
    fit,
    parameter_curves,
)
from arpz.configure.solution import Placement, Solution

Method = Literal["greedy", "exact", "improved"]
METHODS: tuple[Method, ...] = ("greedy", "exact", "improved")


def solve(
    model: Model, *, problem: Literal[1, 2], method: Method, time_limit_s: float = 60.0
) -> Solution:
    """Solve Problem 1 or 2 of a model with one of the three methods."""
    compiled = Problem.build(model, problem)
    if method == "greedy":
        from arpz.configure import greedy

        return greedy.solve(compiled)
    if method == "improved":
        from arpz.configure import improved

        return improved.solve(compiled, time_budget_s=min(time_limit_s, 10.0))
    from arpz.configure import exact  # imports CVXPY: only when asked for

    return exact.solve(compiled, time_limit_s=time_limit_s)


__all__ = [
    "METHODS",
    "Computer",
    "Continuum",
    "Curve",
    "Eq10Node",
    "Eq10Summary",
    "FitError",
    "Link",
    "Loads",
    "Message",
    "Method",
    "Model",
    "ModelError",
    "Node",
    "ParameterCurves",
    "Placement",
    "Problem",
    "Setting",
    "SettingDetail",
    "Solution",
    "best_fit",
    "check",
    "decode_model",
    "dump_json",
    "dump_toml",
    "expand",
    "fit",
    "load_model",
    "loads",
    "node_details",
    "parameter_curves",
    "solve",
    "summarise",
    "validate",
]
