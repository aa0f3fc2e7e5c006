"""A team's planners named in the CEDDP's TOML (``[[planners]]``) and on its command line
(``--planner``), run by a real CEDDP with a real robot through a real router: they get the
fleet's readings, one that raises is counted and never stops the CEDDP or the others, and a
wrong name or option stops the CEDDP before it starts, with a clear error."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.integration.fleet import ceddp, robots, write_robot
from tests.support import wait_until

pytestmark = pytest.mark.integration
REPO = Path(__file__).resolve().parents[2]
ENV = {"PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}


def test_configured_planners_get_readings_and_a_raising_one_is_contained(tmp_path: Path) -> None:
    out = tmp_path / "counting.json"
    extra = (
        '[[planners]]\nclass = "tests.integration.team_nodes:RaisingPlanner"\n'
        '[[planners]]\nclass = "tests.integration.team_nodes:CountingPlanner"\n'
        f'options = {{ out = "{out.as_posix()}" }}\n'
    )
    with ceddp(tmp_path, extra=extra, env=ENV) as (server, endpoint):
        config = write_robot(tmp_path, "robot1", endpoint, preset="machine1", rate_hz=20)
        with robots(tmp_path, [config]):
            wait_until(
                lambda: out.exists() and sum(json.loads(out.read_text())["seen"].values()) >= 20,
                timeout_s=30,
            )
        assert server.interrupt() == 0
    state = json.loads(out.read_text())
    assert state["started"] and state["attached"]
    assert any(key.startswith("robot1/") for key in state["seen"])
    summary = json.loads((tmp_path / "summary.json").read_text())
    raising = summary["planners"]["RaisingPlanner"]
    assert raising["errors"] >= 20
    assert any("ZeroDivisionError" in cause for cause in raising["causes"])
    assert summary["planners"]["CountingPlanner"]["errors"] == 0
    assert any(
        "planner RaisingPlanner raised on_reading: ZeroDivisionError" in e
        for e in summary["events"]
    )
    log = server.output()
    assert log.count("Traceback") >= 1 and "divided by zero" in log
    # once per cause, not once per reading
    assert log.count("planner RaisingPlanner raised in on_reading") < raising["errors"]


def _ceddp_exit(tmp_path: Path, *args: str, toml: str = "") -> subprocess.CompletedProcess[str]:
    config = tmp_path / "ceddp.toml"
    config.write_text('listen = ["tcp/127.0.0.1:0"]\nrrd = "x.rrd"\n' + toml)
    return subprocess.run(
        [sys.executable, "-m", "arpz.ceddp", "--config", str(config), "--duration", "1", *args],
        cwd=tmp_path,
        env={**os.environ, **ENV},
        capture_output=True,
        text=True,
        timeout=60,
    )


@pytest.mark.parametrize(
    ("args", "toml", "says"),
    [
        (("--planner", "tests.integration.team_nodes:Nope"), "", "has no 'Nope'"),
        (("--planner", "no_such_module:Planner"), "", "cannot import module 'no_such_module'"),
        (("--planner", "json:JSONDecoder"), "", "is not a subclass of arpz.ceddp.planner.Planner"),
        (("--planner", "tests.integration.team_nodes"), "", "module.path:ClassName"),
        (
            (),
            '[[planners]]\nclass = "tests.integration.team_nodes:NeedsOptions"\n',
            "NeedsOptions({}) raised KeyError('threshold')",
        ),
        ((), "[[planners]]\noptions = { a = 1 }\n", "class"),
    ],
)
def test_a_wrong_planner_stops_the_ceddp_before_it_starts(
    tmp_path: Path, args: tuple[str, ...], toml: str, says: str
) -> None:
    done = _ceddp_exit(tmp_path, *args, toml=toml)
    assert done.returncode == 2, done.stderr
    assert "bad configuration" in done.stderr and says in done.stderr, done.stderr
    assert "Traceback" not in done.stderr


def test_a_planner_on_the_command_line_runs_beside_the_tomls(tmp_path: Path) -> None:
    out = tmp_path / "counting.json"
    toml = (
        'summary_json = "summary.json"\n'
        '[[planners]]\nclass = "tests.integration.team_nodes:CountingPlanner"\n'
        f'options = {{ out = "{out.as_posix()}" }}\n'
    )
    spec = "tests.integration.team_nodes:RaisingPlanner"
    done = _ceddp_exit(tmp_path, "--planner", spec, toml=toml)
    assert done.returncode == 0, done.stderr
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert sorted(summary["planners"]) == ["CountingPlanner", "RaisingPlanner"]


def test_a_planners_commands_reach_a_configured_actuator(tmp_path: Path) -> None:
    applied = tmp_path / "applied.json"
    extra = '[[planners]]\nclass = "tests.integration.team_nodes:Commander"\n'
    with ceddp(tmp_path, extra=extra, env=ENV) as (server, endpoint):
        actuator = (
            '[actuator]\nclass = "tests.integration.team_nodes:FileActuator"\n'
            f'options = {{ out = "{applied.as_posix()}" }}\n'
        )
        config = write_robot(tmp_path, "robot1", endpoint, preset="machine1", extra=actuator)
        with robots(tmp_path, [config], env=ENV) as (robot,):
            wait_until(
                lambda: applied.exists() and json.loads(applied.read_text())["applied"] >= 20,
                timeout_s=30,
            )
            assert robot.interrupt() == 0
        assert server.interrupt() == 0
    state = json.loads(applied.read_text())
    assert state["name"] == "velocity" and state["value"] == [0.25, -0.5]
    summary = json.loads((tmp_path / "summary.json").read_text())
    velocity = summary["robots"]["robot1"]["downlink"]["velocity"]
    assert velocity["written"] >= 20 and velocity["reconciled"], velocity


@pytest.mark.parametrize(
    ("actuator", "says"),
    [
        ("tests.integration.team_nodes:Mute", "set commands to the names it acts on"),
        ("tests.integration.team_nodes:FileActuator", "FileActuator({}) raised KeyError('out')"),
        (
            "tests.integration.team_nodes:Commander",
            "is not a subclass of arpz.robot.actuation.Actuator",
        ),
    ],
)
def test_a_wrong_actuator_stops_the_robot_before_it_connects(
    tmp_path: Path, actuator: str, says: str
) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "arpz.robot", "--robot-id", "r1", "--actuator", actuator],
        cwd=tmp_path,
        env={**os.environ, **ENV},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2, done.stderr
    assert "bad configuration" in done.stderr and says in done.stderr, done.stderr
