"""An independent feasibility check of a Solution against its model.

It reads the model file's Structs, not the solvers' compiled Problem, and recomputes everything
(loads, link traffic, objective) from the names in the assignment, so a solver bug and a checker
bug would have to coincide to pass unnoticed. Every solver's result goes through it in the tests,
the CLI and the benchmark.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from arpz.configure.model import (
    Model,
    SettingDetail,
    fixed_setting,
    message_bandwidth,
    node_details,
    node_options,
)
from arpz.configure.solution import Solution

_EPS = 1e-6


@dataclass(frozen=True)
class Loads:
    #: CPU placed on each computer
    computer: dict[str, float]
    #: bandwidth on each link, keyed "a - b" as the model lists it, both directions summed
    link: dict[str, float]
    #: messages between computers that have no link: (from, to, computer, computer)
    unlinked: list[tuple[str, str, str, str]]


def link_name(a: str, b: str) -> str:
    return f"{a} - {b}"


def chosen_setting(model: Model, solution: Solution, name: str) -> SettingDetail | None:
    """The node's setting the placement chose, looked up in the MODEL (None if it is none of
    them), so a message following its source's setting is charged that setting's bandwidth."""
    placement = solution.assignment.get(name)
    node = next((n for n in model.nodes if n.name == name), None)
    if placement is None or node is None:
        return None
    if solution.problem == 2:
        fixed = fixed_setting(node)
        candidates = [
            SettingDetail(
                fixed.cpu, fixed.performance, fixed.parameter, fixed.frequency_hz, fixed.bandwidth
            )
        ]
    else:
        candidates = node_details(node)
    for detail in candidates:
        if math.isclose(detail.cpu, placement.cpu, abs_tol=_EPS) and math.isclose(
            detail.performance, placement.performance, abs_tol=_EPS
        ):
            return detail
    return None


def loads(model: Model, solution: Solution) -> Loads:
    computer = {c.name: 0.0 for c in model.computers}
    for placement in solution.assignment.values():
        if placement.computer in computer:
            computer[placement.computer] += placement.cpu
    by_pair = {frozenset(lk.between): link_name(*lk.between) for lk in model.links}
    link = dict.fromkeys(by_pair.values(), 0.0)
    unlinked: list[tuple[str, str, str, str]] = []
    for msg in model.messages:
        a = solution.assignment.get(msg.source)
        b = solution.assignment.get(msg.to)
        if a is None or b is None or a.computer == b.computer:
            continue
        name = by_pair.get(frozenset((a.computer, b.computer)))
        if name is None:
            unlinked.append((msg.source, msg.to, a.computer, b.computer))
        else:
            source = None
            if msg.bandwidth is None:
                source = chosen_setting(model, solution, msg.source)
            link[name] += message_bandwidth(msg, source)
    return Loads(computer=computer, link=link, unlinked=unlinked)


def check(model: Model, solution: Solution) -> list[str]:
    """Every constraint the solution breaks, as readable messages; empty when feasible."""
    if solution.objective is None:
        return [] if not solution.assignment else ["a solution without objective has placements"]
    errors: list[str] = []
    computers = {c.name: c for c in model.computers}
    nodes = {n.name: n for n in model.nodes}
    for name in nodes:
        if name not in solution.assignment:
            errors.append(f"node {name} is not placed")
    for name in solution.assignment:
        if name not in nodes:
            errors.append(f"unknown node {name} in the assignment")

    objective = 0.0
    for name, placement in solution.assignment.items():
        node = nodes.get(name)
        if node is None:
            continue
        if placement.computer not in computers:
            errors.append(f"node {name} is on unknown computer {placement.computer}")
            continue
        if solution.problem == 1:
            valid = node_options(node)
        else:
            fixed = fixed_setting(node)
            valid = [(fixed.cpu, fixed.performance)]
        if not any(
            math.isclose(placement.cpu, u, abs_tol=_EPS)
            and math.isclose(placement.performance, p, abs_tol=_EPS)
            for u, p in valid
        ):
            setting = f"({placement.cpu}, {placement.performance})"
            errors.append(f"node {name}: {setting} is not one of its settings")
        if node.residence is not None and placement.computer not in node.residence:
            errors.append(
                f"node {name} is on {placement.computer}, outside its residence {node.residence}"
            )
        objective += node.weight * placement.performance

    groups: dict[str, set[str]] = {}
    for node in model.nodes:
        if node.coresidence is not None and node.name in solution.assignment:
            groups.setdefault(node.coresidence, set()).add(solution.assignment[node.name].computer)
    for group, where in groups.items():
        if len(where) > 1:
            errors.append(f"coresidence group {group} is split over {sorted(where)}")

    measured = loads(model, solution)
    for name, load in measured.computer.items():
        comp = computers[name]
        if solution.problem == 2 and comp.kind == "server":
            capacity = solution.server_capacity.get(name, 0.0)
        else:
            capacity = comp.capacity
        if load > capacity + _EPS:
            errors.append(f"computer {name}: load {load:g} exceeds capacity {capacity:g}")
    for lk in model.links:
        used = measured.link[link_name(*lk.between)]
        if used > lk.bandwidth + _EPS:
            name = link_name(*lk.between)
            errors.append(f"link {name}: traffic {used:g} exceeds bandwidth {lk.bandwidth:g}")
    for src, dst, ca, cb in measured.unlinked:
        errors.append(f"message {src} -> {dst} crosses {ca} - {cb}, which have no link")

    if solution.problem == 2:
        objective = sum(
            solution.server_capacity.get(c.name, 0.0) for c in model.computers if c.kind == "server"
        )
    if not math.isclose(objective, solution.objective, rel_tol=1e-6, abs_tol=1e-6):
        errors.append(f"objective {solution.objective} differs from the recomputed {objective}")
    return errors
