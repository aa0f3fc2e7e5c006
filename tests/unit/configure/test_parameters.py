"""Fig. 3 regressions (a node's CPU and performance against its parameter) and bandwidth that
depends on the setting, in the model, the solvers and the checker."""

from __future__ import annotations

import itertools

import msgspec
import pytest

from arpz.configure import solve
from arpz.configure.casestudy import case_study
from arpz.configure.check import check, loads
from arpz.configure.model import (
    Computer,
    Continuum,
    Link,
    Message,
    Model,
    Node,
    Setting,
    decode_model,
    node_details,
    validate,
)
from arpz.configure.regression import FitError, parameter_curves

# Table I's Navigation: controller Hz 2, 10, 20 -> CPU 25, 39, 50, performance 10, 65, 100,
# frequency = the Hz, bandwidth 0.1, 0.5, 1.0 KB/s
NAVIGATION = [
    Setting(cpu=25, performance=10, parameter=2, frequency_hz=2, bandwidth=0.1),
    Setting(cpu=39, performance=65, parameter=10, frequency_hz=10, bandwidth=0.5),
    Setting(cpu=50, performance=100, parameter=20, frequency_hz=20, bandwidth=1.0),
]


def test_parameter_at_inverts_the_cpu_curve_and_is_exact_on_a_line() -> None:
    curves = parameter_curves([2, 10], [20, 100], [10, 90], "linear")
    assert curves.cpu.kind == "linear"
    assert curves.parameter_at(60) == pytest.approx(6.0)
    # clamped to the characterised range
    assert curves.parameter_at(5) == 2
    assert curves.parameter_at(500) == 10


def test_best_parameter_fit_keeps_only_curves_that_increase() -> None:
    # Table I's AMCL: particles 200, 500, 3000 -> CPU 19, 41, 66
    curves = parameter_curves([200, 500, 3000], [19, 41, 66], [20, 50, 100], "best")
    low, high = curves.low, curves.high
    samples = [curves.cpu(low + (high - low) * i / 50) for i in range(51)]
    assert all(b > a for a, b in itertools.pairwise(samples))
    # the inversion lands between the characterised parameters, in order
    params = [curves.parameter_at(u) for u in (19, 30, 41, 55, 66)]
    assert params == sorted(params)
    assert params[0] >= 200 and params[-1] <= 3000


def test_a_cpu_curve_that_falls_is_refused() -> None:
    with pytest.raises(FitError, match="does not increase"):
        parameter_curves([1, 2, 3], [10, 30, 20], [1, 2, 3], "poly2")


def test_node_details_interpolate_parameter_frequency_and_bandwidth() -> None:
    node = Node(
        name="navigation",
        settings=NAVIGATION,
        continuum=Continuum(fit="log", step=1, parameter_fit="linear"),
    )
    details = node_details(node)
    assert [d.cpu for d in details] == list(range(25, 51))
    first, last = details[0], details[-1]
    assert (first.parameter, first.frequency_hz) == pytest.approx((2.4, 2.4), abs=1.0)
    assert (last.parameter, last.frequency_hz) == pytest.approx((20, 20), abs=1.0)
    # frequency and bandwidth grow with the parameter, as Table I's columns do
    assert all(b.frequency_hz >= a.frequency_hz for a, b in itertools.pairwise(details))  # type: ignore[operator]
    assert all(b.bandwidth >= a.bandwidth for a, b in itertools.pairwise(details))  # type: ignore[operator]


def test_a_discrete_node_reports_its_listed_values() -> None:
    node = Node(name="navigation", settings=NAVIGATION)
    assert [(d.parameter, d.bandwidth) for d in node_details(node)] == [
        (2, 0.1),
        (10, 0.5),
        (20, 1.0),
    ]


def _two_computers(link_bandwidth: float, *, message_bandwidth: float | None = None) -> Model:
    return Model(
        computers=[
            Computer(name="robot", kind="robot", capacity=100),
            Computer(name="server", kind="server", capacity=100),
        ],
        links=[Link(between=("robot", "server"), bandwidth=link_bandwidth)],
        nodes=[
            Node(name="navigation", residence=["robot"], settings=NAVIGATION),
            Node(name="sink", residence=["server"], settings=[Setting(cpu=1, performance=1)]),
        ],
        messages=[Message(source="navigation", to="sink", bandwidth=message_bandwidth)],
    )


@pytest.mark.parametrize("method", ["greedy", "improved", "exact"])
def test_solutions_report_parameters_and_stay_within_links(method: str) -> None:
    wide = solve(_two_computers(10.0), problem=1, method=method)  # type: ignore[arg-type]
    placed = wide.assignment["navigation"]
    assert (placed.parameter, placed.frequency_hz, placed.bandwidth) == (20, 20, 1.0)
    assert loads(_two_computers(10.0), wide).link["robot - server"] == pytest.approx(1.0)
    # a link that carries only the lowest setting's bandwidth: the solvers reserve the largest
    # (a safe bound), so they find nothing rather than an answer the link cannot carry
    narrow = _two_computers(0.2)
    found = solve(narrow, problem=1, method=method)  # type: ignore[arg-type]
    assert check(narrow, found) == []


def test_the_checker_charges_the_chosen_settings_bandwidth() -> None:
    model = _two_computers(0.3)
    low = solve(_two_computers(10.0), problem=1, method="greedy")
    slow = msgspec.structs.replace(
        low,
        assignment={
            **low.assignment,
            "navigation": msgspec.structs.replace(
                low.assignment["navigation"], cpu=25, performance=10
            ),
        },
        objective=low.objective - 90 if low.objective is not None else None,
    )
    assert loads(model, slow).link["robot - server"] == pytest.approx(0.1)
    assert check(model, slow) == []
    assert any("exceeds bandwidth" in e for e in check(model, low))


def test_a_message_without_bandwidth_needs_its_source_to_give_one() -> None:
    model = _two_computers(10.0)
    bare = msgspec.structs.replace(
        model,
        nodes=[
            Node(name="navigation", residence=["robot"], settings=[Setting(cpu=1, performance=1)]),
            model.nodes[1],
        ],
    )
    assert any("no bandwidth" in p for p in validate(bare))


def test_continuum_fields_on_some_settings_only_are_refused() -> None:
    settings = [NAVIGATION[0], msgspec.structs.replace(NAVIGATION[1], parameter=None)]
    node = Node(name="n", settings=settings, continuum=Continuum(fit="linear"))
    model = Model(computers=[Computer(name="c", kind="robot", capacity=100)], nodes=[node])
    assert any("parameter is given on some settings only" in p for p in validate(model))


def test_old_model_files_load_unchanged() -> None:
    """A model written before these fields (every message with a bandwidth, no parameter
    curves) loads and solves as before."""
    text = (
        b'{"computers": [{"name": "r", "kind": "robot", "capacity": 100}],'
        b' "nodes": [{"name": "a", "settings": [{"cpu": 19, "performance": 20},'
        b' {"cpu": 66, "performance": 100}], "continuum": {"fit": "linear", "step": 1}},'
        b' {"name": "b", "settings": [{"cpu": 1, "performance": 1}]}],'
        b' "messages": [{"from": "a", "to": "b", "bandwidth": 3}]}'
    )
    model = decode_model(text)
    found = solve(model, problem=1, method="greedy")
    assert found.assignment["a"].cpu == 66 and found.assignment["a"].parameter is None


def test_the_case_study_reports_parameters_of_table_i() -> None:
    found = solve(case_study(1, 1, 2), problem=1, method="exact")
    # exact optimum of instance 1: every configurable node at its largest setting
    assert found.assignment["navigation1"].parameter == 20
    assert found.assignment["tracker1"].parameter == 25
    assert found.assignment["model1"].parameter == 10000
