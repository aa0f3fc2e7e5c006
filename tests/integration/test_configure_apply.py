"""seed 002's RQ3 on a real fleet: a solution pushed to a real CEDDP's fleet and 2 robots with a
simulated body, through the CEDDP's router; the robots' sensor rates and the obstacle check's
place change to the solution's, and eq. 10 compares what they measure with what was expected."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.integration.fleet import ceddp, robots
from tests.integration.test_downlink import _mission_robot as sim_robot

pytestmark = pytest.mark.integration

#: robot1 has room for its obstacle beam at 6 Hz only if the obstacle check runs on the server
#: (which holds one check); robot2 has room for both at 10 Hz. Exact optimum, printed by
#: ``python -m arpz.configure solve`` on this model: lidar1 6 Hz, lidar2 10 Hz, obstacle1 on
#: the server, obstacle2 on robot2.
MODEL = """name = "two sim robots: the obstacle beam's rate and where the obstacle check runs"

[[computers]]
name = "robot1"
kind = "robot"
capacity = 6

[[computers]]
name = "robot2"
kind = "robot"
capacity = 20

[[computers]]
name = "server"
kind = "server"
capacity = 1

[[links]]
between = ["robot1", "server"]
bandwidth = 1000

[[links]]
between = ["robot2", "server"]
bandwidth = 1000

[[nodes]]
name = "lidar1"
topic = "robot1/lidar_0"
residence = ["robot1"]
continuum = {fit = "linear", step = 1, parameter_fit = "linear"}
settings = [{cpu = 2, performance = 20, parameter = 2, frequency_hz = 2, bandwidth = 20},
            {cpu = 10, performance = 100, parameter = 10, frequency_hz = 10, bandwidth = 100}]

[[nodes]]
name = "lidar2"
topic = "robot2/lidar_0"
residence = ["robot2"]
continuum = {fit = "linear", step = 1, parameter_fit = "linear"}
settings = [{cpu = 2, performance = 20, parameter = 2, frequency_hz = 2, bandwidth = 20},
            {cpu = 10, performance = 100, parameter = 10, frequency_hz = 10, bandwidth = 100}]

[[nodes]]
name = "obstacle1"
computation = "robot1/obstacle_check"
residence = ["robot1", "server"]
settings = [{cpu = 1, performance = 100}]

[[nodes]]
name = "obstacle2"
computation = "robot2/obstacle_check"
residence = ["robot2", "server"]
settings = [{cpu = 1, performance = 100}]

[[messages]]
from = "lidar1"
to = "obstacle1"

[[messages]]
from = "lidar2"
to = "obstacle2"
"""


def test_apply_a_solution_to_a_running_fleet(tmp_path: Path) -> None:
    model = tmp_path / "fleet.toml"
    model.write_text(MODEL)
    out = tmp_path / "apply.json"
    with ceddp(tmp_path) as (_server, endpoint):
        configs = [sim_robot(tmp_path, r, endpoint) for r in ("robot1", "robot2")]
        with robots(tmp_path, configs) as procs:
            proc = subprocess.run(
                [
                    sys.executable,
                    "-m",
                    "arpz.configure",
                    "apply",
                    str(model),
                    "--connect",
                    endpoint,
                    "--fleet",
                    "itest",
                    "--method",
                    "exact",
                    "--settle",
                    "1.0",
                    "--duration",
                    "3",
                    "--json",
                    str(out),
                ],
                capture_output=True,
                text=True,
                timeout=60,
            )
            logs = "\n".join(p.output() for p in procs)
    assert proc.returncode == 0, (proc.stdout, proc.stderr, logs)
    result = json.loads(out.read_text())
    assert result["problems"] == []
    sent = result["configuration"]["robots"]
    assert sent["robot1"] == {
        "rates_hz": {"lidar_0": 6.0},
        "computations": {"obstacle_check": "ceddp"},
    }
    assert sent["robot2"] == {
        "rates_hz": {"lidar_0": 10.0},
        "computations": {"obstacle_check": "robot"},
    }
    # each robot answered with what it runs now: the planned beam at its new rate, the other
    # seven beams still at their configured 20 Hz
    for robot, rate, place in (("robot1", 6.0, "ceddp"), ("robot2", 10.0, "robot")):
        ack = result["acks"][robot]
        assert ack["refused"] == []
        assert ack["rates_hz"]["lidar_0"] == rate
        assert ack["rates_hz"]["lidar_90"] == 20.0
        assert ack["computations"] == {"obstacle_check": place}
    assert "configuration epoch" in logs and "applied" in logs
    # eq. 10: the beams were measured at their new rates (arrived + held back), so the measured
    # performance is close to the expected one, node by node and overall
    eq10 = result["eq10"]
    assert eq10["not_measured"] == []
    by_node = {n["node"]: n for n in eq10["nodes"]}
    assert by_node["lidar1"]["f_expected_hz"] == 6.0
    assert by_node["lidar2"]["f_expected_hz"] == 10.0
    for node in by_node.values():
        assert node["f_measured_hz"] == pytest.approx(node["f_expected_hz"], rel=0.3), node
    assert eq10["expected"] == pytest.approx(160.0)  # 60 + 100: the two beams' performance
    assert abs(eq10["deviation"]) < 0.3
    assert "overall sum(w P)" in proc.stdout
