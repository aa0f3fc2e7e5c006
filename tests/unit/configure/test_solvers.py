"""Solvers against an independent brute force, and the checker against hand-made violations."""

from __future__ import annotations

import itertools
import time

import msgspec
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from arpz.configure import exact, greedy, improved
from arpz.configure.casestudy import paper_instance
from arpz.configure.check import check
from arpz.configure.model import (
    Computer,
    Link,
    Message,
    Model,
    Node,
    Setting,
    fixed_setting,
    node_options,
    validate,
)
from arpz.configure.problem import Problem
from arpz.configure.solution import Placement, Solution


def brute_force(model: Model, kind: int) -> float | None:
    """Best objective over every placement and setting, feasibility judged by check() alone."""
    names = [c.name for c in model.computers]
    per_node = []
    for node in model.nodes:
        if kind == 1:
            opts = node_options(node)
        else:
            f = fixed_setting(node)
            opts = [(f.cpu, f.performance)]
        per_node.append([(c, u, p) for c in names for u, p in opts])
    best: float | None = None
    for combo in itertools.product(*per_node):
        assignment = {
            n.name: Placement(computer=c, cpu=u, performance=p)
            for n, (c, u, p) in zip(model.nodes, combo, strict=True)
        }
        if kind == 1:
            objective = sum(
                n.weight * a.performance
                for n, a in zip(model.nodes, assignment.values(), strict=True)
            )
            server_capacity: dict[str, float] = {}
        else:
            server_capacity = {c.name: 0.0 for c in model.computers if c.kind == "server"}
            for a in assignment.values():
                if a.computer in server_capacity:
                    server_capacity[a.computer] += a.cpu
            objective = sum(server_capacity.values())
        candidate = Solution(
            problem=kind,
            method="brute",
            status="feasible",
            objective=objective,
            assignment=assignment,
            server_capacity=server_capacity,
        )
        if check(model, candidate):
            continue
        if best is None or (objective > best if kind == 1 else objective < best):
            best = objective
    return best


@st.composite
def small_models(draw, max_nodes: int = 4) -> Model:
    n_comp = draw(st.integers(1, 3))
    computers = [
        Computer(
            name=f"c{i}",
            kind=draw(st.sampled_from(["robot", "server"])),
            capacity=draw(st.integers(5, 60)),
        )
        for i in range(n_comp)
    ]
    links = []
    for i, j in itertools.combinations(range(n_comp), 2):
        if draw(st.booleans()):
            links.append(Link(between=(f"c{i}", f"c{j}"), bandwidth=draw(st.integers(0, 6))))
    nodes = []
    n_nodes = draw(st.integers(1, max_nodes))
    for k in range(n_nodes):
        n_set = draw(st.integers(1, 3))
        settings_ = [
            Setting(cpu=draw(st.integers(1, 30)), performance=draw(st.integers(0, 100)))
            for _ in range(n_set)
        ]
        residence = None
        if draw(st.booleans()):
            residence = sorted({f"c{draw(st.integers(0, n_comp - 1))}" for _ in range(2)})
        coresidence = draw(st.sampled_from([None, None, "g"]))
        nodes.append(
            Node(
                name=f"n{k}",
                weight=draw(st.sampled_from([0.1, 0.25, 0.5, 1.0])),
                settings=settings_,
                residence=residence,
                coresidence=coresidence,
            )
        )
    messages = []
    for a, b in itertools.permutations(range(n_nodes), 2):
        if draw(st.integers(0, 3)) == 0:
            messages.append(Message(source=f"n{a}", to=f"n{b}", bandwidth=draw(st.integers(1, 4))))
    model = Model(computers=computers, links=links, nodes=nodes, messages=messages)
    assume(not validate(model))
    return model


FAST = settings(
    max_examples=60,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
)


@FAST
@given(small_models(), st.sampled_from([1, 2]))
def test_exact_matches_brute_force(model, kind):
    expected = brute_force(model, kind)
    result = exact.solve(Problem.build(model, kind), time_limit_s=20)
    assert check(model, result) == []
    if expected is None:
        assert result.objective is None and result.status == "infeasible"
    else:
        assert result.status == "optimal"
        assert result.objective == pytest.approx(expected, abs=1e-6)


@FAST
@given(small_models(max_nodes=5), st.sampled_from([1, 2]))
def test_greedy_and_improved_answers_are_always_feasible(model, kind):
    problem = Problem.build(model, kind)
    for solver in (greedy, improved):
        result = solver.solve(problem)
        assert check(model, result) == [], (solver.METHOD, result)
        assert result.status in ("feasible", "infeasible")


@pytest.mark.parametrize("number", [1, 2, 3, 4, 5, 6])
def test_paper_instances_order_of_methods(number):
    model = paper_instance(number)
    for kind in (1, 2):
        problem = Problem.build(model, kind)
        best = exact.solve(problem, time_limit_s=30)
        assert best.status == "optimal" and check(model, best) == []
        for solver in (greedy, improved):
            got = solver.solve(problem)
            assert check(model, got) == [] and got.objective is not None
            if kind == 1:
                assert got.objective <= best.objective + 1e-6
            else:
                assert got.objective >= best.objective - 1e-6
        near = improved.solve(problem).objective
        assert abs(near - best.objective) <= 0.01 * abs(best.objective)


def test_improved_beats_greedy_where_the_convex_curve_hurts_it():
    # Instance 5: the greedy's gradient rule starves the convex AMCL curve.
    problem = Problem.build(paper_instance(5), 1)
    assert improved.solve(problem).objective > greedy.solve(problem).objective + 1.0


# -- the checker against hand-made violations -------------------------------------------------

TWO = Model(
    computers=[
        Computer(name="r", kind="robot", capacity=10),
        Computer(name="s", kind="server", capacity=100),
        Computer(name="t", kind="server", capacity=100),
    ],
    links=[Link(between=("r", "s"), bandwidth=3)],
    nodes=[
        Node(name="a", settings=[Setting(cpu=6, performance=1)], residence=["r", "s"]),
        Node(name="b", settings=[Setting(cpu=6, performance=2)], coresidence="g"),
        Node(name="c", settings=[Setting(cpu=1, performance=3)], coresidence="g"),
    ],
    messages=[Message(source="a", to="b", bandwidth=2), Message(source="c", to="a", bandwidth=2)],
)


def _sol(where: dict[str, str], objective: float = 6.0) -> Solution:
    perf = {"a": (6, 1), "b": (6, 2), "c": (1, 3)}
    return Solution(
        problem=1,
        method="hand",
        status="feasible",
        objective=objective,
        assignment={
            n: Placement(computer=c, cpu=perf[n][0], performance=perf[n][1])
            for n, c in where.items()
        },
    )


def test_checker_accepts_a_feasible_answer_and_counts_same_computer_messages_free():
    assert check(TWO, _sol({"a": "s", "b": "s", "c": "s"})) == []


def test_checker_counts_both_directions_on_one_link():
    errors = check(TWO, _sol({"a": "r", "b": "s", "c": "s"}))
    assert any("r - s: traffic 4 exceeds bandwidth 3" in e for e in errors)


def test_checker_finds_each_kind_of_violation():
    assert any("exceeds capacity" in e for e in check(TWO, _sol({"a": "r", "b": "r", "c": "r"})))
    assert any("no link" in e for e in check(TWO, _sol({"a": "s", "b": "t", "c": "t"})))
    assert any(
        "outside its residence" in e for e in check(TWO, _sol({"a": "t", "b": "t", "c": "t"}))
    )
    assert any("split" in e for e in check(TWO, _sol({"a": "s", "b": "s", "c": "t"})))
    assert any("objective" in e for e in check(TWO, _sol({"a": "s", "b": "s", "c": "s"}, 7.0)))
    assert any("not placed" in e for e in check(TWO, _sol({"a": "s", "b": "s"})))


@settings(
    max_examples=15,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
)
@given(small_models(), st.sampled_from([1, 2]))
def test_the_highspy_backend_with_warm_start_agrees_with_brute_force(model, kind):
    expected = brute_force(model, kind)
    result = exact.solve(
        Problem.build(model, kind), time_limit_s=20, backend="highs", warm_start=True
    )
    assert check(model, result) == []
    if expected is None:
        assert result.objective is None
    else:
        assert result.objective == pytest.approx(expected, abs=1e-6)


def test_exact_reports_a_time_limit_with_a_valid_bound():
    # 40 robots whose messages constrain the placement cannot be proved optimal in 1 s (the gap
    # is still 6-9 % when it stops, also with a second process loading the CPU; 10 robots, as
    # this test once used, are solved outright, so it checked nothing; at 0.2 s a loaded CI host
    # sometimes stopped before HiGHS had any bound); what comes back must still be feasible and
    # its bound must not be below its own objective (Problem 1 maximises). A CI host busy with
    # the other test worker once stopped at 1 s before HiGHS had any bound: then no gap may be
    # claimed either, and the test tries again with 4 s, still far from a proof of optimality.
    from arpz.configure.casestudy import case_study

    model = case_study(40, 8, 48)
    problem = Problem.build(model, 1)
    result = exact.solve(problem, time_limit_s=1.0)
    if result.bound is None:
        assert result.gap is None, result
        result = exact.solve(problem, time_limit_s=4.0)
    assert result.status == "time_limit", result
    assert check(model, result) == []
    assert result.objective is not None and result.bound is not None, result
    assert result.bound >= result.objective - 1e-6
    assert result.gap is not None and result.gap >= 0


def test_improved_repairs_a_seed_that_overloads_a_link():
    model = Model(
        computers=[
            Computer(name="r", kind="robot", capacity=50),
            Computer(name="s", kind="server", capacity=50),
        ],
        links=[Link(between=("r", "s"), bandwidth=1)],
        nodes=[
            Node(
                name="a", settings=[Setting(cpu=10, performance=1), Setting(cpu=30, performance=5)]
            ),
            Node(
                name="b", settings=[Setting(cpu=10, performance=1), Setting(cpu=30, performance=5)]
            ),
        ],
        messages=[Message(source="a", to="b", bandwidth=2)],
    )
    problem = Problem.build(model, 1)
    state = improved._seeded(problem, [0, 1])  # a on r, b on s: 2 > 1 on the link
    assert state is not None and state.link_load == [2.0]
    assert improved._Search(problem, state).repair(time.perf_counter() + 5)
    assert state.link_load == [0.0] and state.computer[0] == state.computer[1]
    apart = improved.solve(problem, seed=[0, 1])
    assert check(model, apart) == []
    assert apart.assignment["a"].computer == apart.assignment["b"].computer
    # a seed outside a residence is ignored, not trusted
    pinned = msgspec.structs.replace(
        model, nodes=[msgspec.structs.replace(model.nodes[0], residence=["s"]), model.nodes[1]]
    )
    result = improved.solve(Problem.build(pinned, 1), seed=[0, 0])
    assert check(pinned, result) == [] and result.assignment["a"].computer == "s"


@pytest.mark.parametrize("backend", ["highs", "cvxpy"])
def test_a_solver_point_that_breaks_the_model_is_no_solution(
    backend: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """At a time limit HiGHS (through CVXPY) once handed back all zeros as its solution, which
    placed no unit and crashed the decoding; such a point is refused, whatever the status."""
    import numpy as np

    lp = exact._Lp()
    a, b = lp.var(0, 2, integer=True, obj=1.0), lp.var(0, 2, integer=True, obj=2.0)
    lp.eq.append(({a: 1.0, b: 1.0}, 2.0))  # place both units
    zeros = ("time_limit", np.zeros(2), 4.0, "time limit hit")
    method = "_solve_cvxpy" if backend == "cvxpy" else "_solve_highs"
    monkeypatch.setattr(exact._Lp, method, lambda self, **kw: zeros)
    status, x, bound, message = lp.solve(maximise=True, time_limit_s=1.0, backend=backend)
    assert (status, x, bound) == ("time_limit", None, 4.0), message
    monkeypatch.undo()
    status, x, _, _ = lp.solve(maximise=True, time_limit_s=5.0, backend=backend)
    assert status == "optimal" and x is not None and list(np.round(x)) == [0.0, 2.0]
