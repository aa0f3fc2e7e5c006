"""The ``optimise`` command: text and JSON output, exit codes, and the module entry point."""

from __future__ import annotations

import contextlib
import io
import json
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from arpz.ceddp.optimise_cli import main
from arpz.ceddp.optimiser import InfeasibleQosError, QosLimits, solve_closed


def test_text_output_for_the_paper_machines(capsys: pytest.CaptureFixture[str]) -> None:
    # T = 6,5,5, Rmax 100, Rmin 1: R = 17.75 Hz (deadline 1/17.75 = 56.3 ms), D = 886.
    code = main(["--rmax", "100", "--rmin", "1", "--topics", "6,5,5"])
    out = capsys.readouterr().out
    assert code == 0
    assert "R         17.75 Hz  (deadline period 56.3 ms)" in out
    assert "D         886 samples" in out
    assert "T_avg = 5.333" in out
    assert "binding   (4) Rmax/T_avg - R >= Rmin; (5) Dmax*R/Rmax - D >= Dmin" in out
    assert "solve time closed" in out


def test_json_has_the_required_keys(capsys: pytest.CaptureFixture[str]) -> None:
    # T = 7,6,6 (eq. 1 with the received topic), Rmax 1000: R = 2981/19, D = 783.
    code = main(["--rmax", "1000", "--rmin", "1", "--topics", "7,6,6", "--json"])
    document = json.loads(capsys.readouterr().out)
    assert code == 0
    assert document["R"] == pytest.approx(2981 / 19)
    assert document["D"] == 783
    assert document["T_avg"] == pytest.approx(19 / 3)
    assert document["deadline_s"] == pytest.approx(19 / 2981)
    assert document["topics"] == [7, 6, 6]


def test_loss_aware_options_and_policy(capsys: pytest.CaptureFixture[str]) -> None:
    # Rmax 100, T 6,5,5: R = 17.75; 10 % loss, 20 ms RTT. arpz's sensor profile by default
    # (heartbeat 100 ms, NACK delay 2 ms): 9 rounds of 0.122 s, ceil(17.75 x 1.098) = 20;
    # Fast DDS timings: 484 samples (hand-computed in test_optimiser); Cyclone-like
    # 100 ms/100 ms: round 0.22 s, 9 rounds = 1.98 s, ceil(17.75 * 1.98) = ceil(35.145) = 36.
    argv = ["--rmax", "100", "--rmin", "1", "--topics", "6,5,5", "--rtt-ms", "20"]
    assert main([*argv, "--loss-pct", "10", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["loss_aware"]["depth"] == 20
    fastdds = ["--heartbeat-ms", "3000", "--nack-delay-ms", "5"]
    assert main([*argv, "--loss-pct", "10", *fastdds, "--json"]) == 0
    document = json.loads(capsys.readouterr().out)
    assert document["loss_aware"]["depth"] == 484
    assert document["paper_loss_safe"] is True
    cyclone = ["--loss-pct", "10", "--heartbeat-ms", "100", "--nack-delay-ms", "100"]
    assert main([*argv, *cyclone, "--depth-policy", "loss_aware", "--json"]) == 0
    document = json.loads(capsys.readouterr().out)
    assert (document["D"], document["paper_D"]) == (36, 886)
    assert main([*argv, "--loss-pct", "10"]) == 0
    assert "paper D covers it: yes" in capsys.readouterr().out


def test_both_methods_print_both_times_and_ratio(capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["--rmax", "200", "--rmin", "1", "--topics", "6,5,5", "--method", "both"])
    out = capsys.readouterr().out
    assert code == 0
    assert "D         911 samples" in out
    assert "cvxpy/closed =" in out


@pytest.mark.parametrize(
    ("argv", "fragment"),
    [
        (
            ["--rmax", "480", "--rmin", "50", "--topics", "6,6,6"],
            "raise Rmax to at least 600 Hz or lower Rmin to at most 40 Hz",
        ),
        (["--rmax", "100", "--rmin", "1", "--topics", "6,x"], "topic counts per agent"),
        (["--rmax", "100", "--rmin", "1", "--topics", "6,0"], "agent 1 must be an integer >= 1"),
        (["--rmin", "1", "--topics", "6"], "--rmax"),
        (["--rmax", "100", "--rmin", "1", "--topics", "6", "--rtt-ms", "5"], "--loss-pct"),
        (["--rmax", "100", "--rmin", "1", "--dmin", "9", "--dmax", "8", "--topics", "6"], "dmin"),
        (["--rmax", "-1", "--rmin", "1", "--topics", "6"], "rmax_hz must be a finite rate > 0"),
        (["--rmax", "1", "--rmin", "1", "--topics", "6", "--method", "magic"], "--method"),
        (
            ["--rmax", "100", "--rmin", "1", "--topics", "6", "--depth-policy", "max"],
            "needs the link quality",
        ),
    ],
)
def test_errors_go_to_stderr_with_exit_code_2(
    argv: list[str], fragment: str, capsys: pytest.CaptureFixture[str]
) -> None:
    code = main(argv)
    captured = capsys.readouterr()
    assert code == 2
    assert fragment in captured.err
    assert captured.out == ""


def test_help_exits_zero(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--help"]) == 0
    assert "--topics" in capsys.readouterr().out


@given(
    st.lists(st.integers(min_value=1, max_value=12), min_size=1, max_size=6),
    st.floats(min_value=10, max_value=5000),
    st.floats(min_value=1e-4, max_value=1.0),
    st.integers(min_value=1, max_value=50),
)
@settings(max_examples=40, deadline=None)
def test_json_matches_the_api(
    topics: list[int], rmax: float, rmin_fraction: float, dmin: int
) -> None:
    rmin = rmax * rmin_fraction
    argv = ["--rmax", repr(rmax), "--rmin", repr(rmin), "--dmin", str(dmin)]
    argv += ["--topics", ",".join(map(str, topics)), "--json"]
    code, out = _run(argv)
    try:
        expected = solve_closed(QosLimits(rmax_hz=rmax, rmin_hz=rmin, dmin=dmin), topics)
    except InfeasibleQosError:
        assert (code, out) == (2, "")
        return
    assert code == 0
    document = json.loads(out)
    assert document["R"] == expected.rate_hz
    assert document["D"] == expected.depth
    assert document["T_avg"] == expected.t_avg
    assert document["binding"] == list(expected.binding)


def _run(argv: list[str]) -> tuple[int, str]:
    """main() with stdout captured, usable inside a hypothesis test (no function fixtures)."""
    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer), contextlib.redirect_stderr(io.StringIO()):
        code = main(argv)
    return code, buffer.getvalue()


def test_module_entry_point_prints_one_json_object() -> None:
    # --method cvxpy too: a solver banner on stdout would break the single JSON object.
    argv = ["--rmax", "500", "--rmin", "1", "--topics", "6,5,5", "--json", "--method", "cvxpy"]
    completed = subprocess.run(
        [sys.executable, "-m", "arpz.ceddp.optimise_cli", *argv],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert completed.returncode == 0, completed.stderr
    document = json.loads(completed.stdout)  # the whole of stdout is one object
    # Rmax 500, T_avg 16/3: R = 1500/16 - 1 = 92.75, D = floor(937.5 - 10 - 1) = 926.
    assert document["R"] == pytest.approx(92.75, abs=5e-4)
    assert document["D"] == 926
    assert document["method"] == "cvxpy"


def test_module_entry_point_infeasible_exit_code() -> None:
    argv = ["--rmax", "480", "--rmin", "50", "--topics", "6,6,6", "--json"]
    completed = subprocess.run(
        [sys.executable, "-m", "arpz.ceddp.optimise_cli", *argv],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert completed.returncode == 2
    assert completed.stdout == ""
    assert "Rmax/T_avg - Rmin = 80 - 50 = 30 < Rmin = 50" in completed.stderr


# ------------------------------------------------------------------ --problem FILE.toml


def _problem(tmp_path: Path, text: str) -> str:
    path = tmp_path / "problem.toml"
    path.write_text(text, encoding="utf-8")
    return str(path)


_ALIKE = """
rmax_hz = 100.0
rmin_hz = 1.0
[[robots]]
name = "robot1"
topics = [{name = "a"}, {name = "b"}, {name = "c"}, {name = "d"}, {name = "e"}, {name = "f"}]
[[robots]]
name = "robot2"
topics = [{name = "a"}, {name = "b"}, {name = "c"}, {name = "d"}, {name = "e"}]
[[robots]]
name = "robot3"
topics = [{name = "a", weight = 1.0}, {name = "b"}, {name = "c"}, {name = "d"}, {name = "e"}]
"""


def test_problem_file_with_alike_topics_gives_seed_001(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # T = 6,5,5, Rmax 100: seed 001's R = 17.75 Hz, D = 886 for every topic
    assert main(["--problem", _problem(tmp_path, _ALIKE), "--json"]) == 0
    document = json.loads(capsys.readouterr().out)
    assert len(document["topics"]) == 16
    assert {(t["R"], t["D"]) for t in document["topics"]} == {(17.75, 886)}
    assert document["fleet"] == {"R": 17.75, "D": 886}
    assert document["topics"][0]["robot"] == "robot1" and document["topics"][0]["topic"] == "a"


def test_problem_file_weights_and_both_methods(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # one robot, C = 100 - 2 = 98, weights 1 x sqrt(1) and 3 x sqrt(1): 24.5 and 73.5 Hz
    text = (
        'rmax_hz = 100.0\nrmin_hz = 1.0\n[[robots]]\nname = "r"\n'
        'topics = [{name = "pir", weight = 1.0, change_hz = 1.0},'
        ' {name = "lidar", weight = 3.0, change_hz = 1.0}]\n'
    )
    assert main(["--problem", _problem(tmp_path, text), "--method", "both", "--json"]) == 0
    document = json.loads(capsys.readouterr().out)
    assert [t["R"] for t in document["topics"]] == [24.5, 73.5]
    assert set(document["solve_times_s"]) == {"closed", "cvxpy"}
    assert main(["--problem", _problem(tmp_path, text)]) == 0
    assert "lidar" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        (
            'rmax_hz = 100.0\nrmin_hz = 1.0\n[[robots]]\nname = "r"\n'
            'topics = [{name = "x", weight = "high"}]\n',
            "robots[0].topics[0].weight",
        ),
        (
            'rmax_hz = 100.0\nrmin_hz = 1.0\n[[robots]]\nname = "r"\n'
            'topics = [{name = "x", weight = -1.0}]\n',
            "robots[0].topics[0]: topic 'x'",
        ),
        ('rmin_hz = 1.0\n[[robots]]\nname = "r"\ntopics = [{name = "x"}]\n', "rmax_hz"),
        (
            'rmax_hz = 100.0\nrmin_hz = 1.0\n[[robots]]\nname = "r"\n'
            'topics = [{name = "x", colour = 1}]\n',
            "colour",
        ),
        ("rmax_hz = 100.0\nrmin_hz = 1.0\nrobots = []\n", "no [[robots]]"),
        ("rmax_hz = = 1\n", "not valid TOML"),
        (
            'rmax_hz = 10.0\nrmin_hz = 3.0\n[[robots]]\nname = "r"\n'
            'topics = [{name = "x"}, {name = "y"}]\n',
            "infeasible: constraint (4)",
        ),
    ],
)
def test_bad_problem_files_exit_2_naming_the_field(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, fragment: str
) -> None:
    assert main(["--problem", _problem(tmp_path, text), "--json"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert fragment in captured.err


def test_missing_problem_file_and_mixed_options(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["--problem", str(tmp_path / "none.toml")]) == 2
    assert "cannot read the problem file" in capsys.readouterr().err
    argv = ["--problem", _problem(tmp_path, _ALIKE), "--topics", "6"]
    assert main(argv) == 2
    assert "either --problem or --topics" in capsys.readouterr().err


def test_the_example_problem_runs_from_the_entry_point() -> None:
    example = Path(__file__).resolve().parents[3] / "examples" / "qos_problem.toml"
    run = subprocess.run(
        [sys.executable, "-m", "arpz.ceddp", "optimise", "--problem", str(example), "--json"],
        capture_output=True,
        text=True,
        check=False,
        timeout=60,
    )
    assert run.returncode == 0, run.stderr
    document = json.loads(run.stdout)
    rates = {(t["robot"], t["topic"]): t["R"] for t in document["topics"]}
    # the LIDAR (priority 2, changes at 20 Hz) outranks the PIR (0.05 Hz) as sqrt and weights say
    assert rates["robot1", "lidar"] > 10 * rates["robot1", "pir"]
    assert sum(rates.values()) == pytest.approx(document["capacity_hz"])
