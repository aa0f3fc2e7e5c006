"""The CLI as a user runs it: subprocesses, exit codes, one JSON object with --json."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from arpz.configure.check import check
from arpz.configure.model import load_model
from arpz.configure.solution import Placement, Solution


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "arpz.configure", *args], capture_output=True, text=True, timeout=120
    )


@pytest.fixture(scope="module")
def instance4(tmp_path_factory):
    path = tmp_path_factory.mktemp("cli") / "i4.toml"
    proc = run(
        "instance",
        "--robots",
        "2",
        "--cameras",
        "1",
        "--computers",
        "3",
        "--format",
        "toml",
        "--out",
        str(path),
    )
    assert proc.returncode == 0, proc.stderr
    return path


@pytest.mark.parametrize(
    ("method", "problem"), [("greedy", "1"), ("improved", "2"), ("exact", "1"), ("exact", "2")]
)
def test_solve_json_is_one_feasible_object(instance4, method, problem):
    proc = run("solve", str(instance4), "--problem", problem, "--method", method, "--json")
    assert proc.returncode == 0, proc.stderr
    data = json.loads(proc.stdout)
    assert data["status"] in ("optimal", "feasible")
    model = load_model(instance4)
    assert set(data["assignment"]) == {n.name for n in model.nodes}
    # re-check what the CLI printed, independently of the solver's own objects
    solution = Solution(
        problem=int(problem),
        method=method,
        status=data["status"],
        objective=data["objective"],
        server_capacity=data["server_capacity"],
        assignment={k: Placement(**v) for k, v in data["assignment"].items()},
    )
    assert check(model, solution) == []
    assert data["violations"] == []
    # the paper's AMCL curve (Figure 4), fitted from Table I's three settings
    assert data["curves"]["amcl1"]["fit"] == "poly2"
    assert data["curves"]["amcl1"]["equation"].startswith("P = 135.4 x^2 + 55.126 x")


def test_solve_text_has_nodes_computers_and_links(instance4):
    proc = run("solve", str(instance4), "--method", "exact", "--time-limit", "30")
    assert proc.returncode == 0, proc.stderr
    assert "status     optimal" in proc.stdout
    for needle in ("youbot_core1", "robot1 - server1", "capacity", "bandwidth", "solve time"):
        assert needle in proc.stdout


def test_bad_model_exits_2_naming_the_file_and_the_problem(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(
        json.dumps(
            {
                "computers": [{"name": "r", "kind": "robot", "capacity": 100}],
                "links": [{"between": ["r", "nowhere"], "bandwidth": 1}],
                "nodes": [{"name": "a", "settings": []}],
            }
        )
    )
    proc = run("solve", str(bad), "--method", "greedy")
    assert proc.returncode == 2
    assert "bad.json" in proc.stderr
    assert "unknown computer 'nowhere'" in proc.stderr and "settings is empty" in proc.stderr


def test_infeasible_model_exits_3(tmp_path):
    path = tmp_path / "tight.json"
    path.write_text(
        json.dumps(
            {
                "computers": [{"name": "r", "kind": "robot", "capacity": 10}],
                "nodes": [{"name": "a", "settings": [{"cpu": 20, "performance": 1}]}],
            }
        )
    )
    proc = run("solve", str(path), "--method", "exact", "--json")
    assert proc.returncode == 3
    assert json.loads(proc.stdout)["status"] == "infeasible"


def test_fit_reports_the_three_curves_and_the_choice(tmp_path):
    points = tmp_path / "amcl.csv"
    points.write_text("cpu,performance\n19,20\n41,50\n66,100\n")
    proc = run("fit", str(points), "--json")
    assert proc.returncode == 0, proc.stderr
    data = json.loads(proc.stdout)
    assert {c["kind"] for c in data["candidates"]} == {"linear", "log", "poly2"}
    assert data["chosen"]["kind"] == "poly2"
    bad = tmp_path / "bad.csv"
    bad.write_text("cpu,performance\n19,abc\n")
    proc = run("fit", str(bad))
    assert proc.returncode == 2 and "bad.csv" in proc.stderr


def test_the_example_runs_and_the_exact_method_is_never_beaten():
    proc = subprocess.run(
        [sys.executable, "examples/configure_compare.py"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    for problem in ("Problem 1", "Problem 2"):
        block = proc.stdout.split(problem)[1].splitlines()[1:4]
        values = {line.split()[0]: float(line.split()[2]) for line in block}
        if problem == "Problem 1":
            assert values["exact"] >= max(values["greedy"], values["improved"]) - 1e-6
        else:
            assert values["exact"] <= min(values["greedy"], values["improved"]) + 1e-6


def test_figure5_prints_a_table_and_draws_the_figure(tmp_path):
    png = tmp_path / "figure5.png"
    proc = run("figure5", "--instances", "2", "--time-limit", "20", "--png", str(png))
    assert proc.returncode == 0, proc.stderr
    rows = [
        line
        for line in proc.stdout.splitlines()
        if line.startswith("| 1 ") or line.startswith("| 2 ")
    ]
    assert len(rows) == 4  # two instances x two problems
    for row in rows:
        cells = [c.strip() for c in row.strip("|").split("|")]
        assert cells[4] == "optimal"
        greedy_ratio, improved_ratio = float(cells[6]), float(cells[7])
        if cells[1] == "1":
            assert greedy_ratio <= 1 + 1e-9 and improved_ratio <= 1 + 1e-9
        else:
            assert greedy_ratio >= 1 - 1e-9 and improved_ratio >= 1 - 1e-9
    assert png.stat().st_size > 10_000
