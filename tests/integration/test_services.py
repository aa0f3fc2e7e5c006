"""Robot services through a real router: a real robot process serves ``[[services]]`` handlers
(tests/integration/service_handlers.py), a real CEDDP routes, and real callers call them:
``python -m arpz service`` (as a process and in this process) and ``ServiceCaller`` on a client
session. Every outcome is checked at the caller and reconciled with the robot's own counts in the
CEDDP's summary."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from arpz.ceddp.services import (
    NoSuchService,
    RobotGone,
    ServiceCaller,
    ServiceFailed,
    ServiceTimeout,
)
from arpz.core.transport import SessionSettings
from arpz.tools.service import main as service_main
from arpz.transport.zenoh import ZenohTransport
from tests.integration.fleet import ceddp, robots, write_robot
from tests.integration.service_handlers import SERVICES, SLOW_S
from tests.support import router, wait_until

pytestmark = pytest.mark.integration
REPO = Path(__file__).resolve().parents[2]
ENV = {"PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
FLEET = "itest"
TRIGGER = "std_srvs/srv/Trigger"


def cli(tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "arpz", "service", *args],
        cwd=tmp_path,
        env={**os.environ, **ENV},
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_a_robot_serves_the_cli_and_a_service_caller_and_both_ends_count(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with ceddp(tmp_path, env=ENV) as (server, endpoint):
        config = write_robot(tmp_path, "robot1", endpoint, preset="machine1", rate_hz=5)
        config.write_text(config.read_text() + SERVICES)
        where = ["--connect", endpoint, "--fleet", FLEET]
        with robots(tmp_path, [config], env=ENV) as (robot,):
            # the CLI as a process: list, a call answered, a handler that raises
            listed = cli(tmp_path, "list", *where, "--json")
            assert listed.returncode == 0, listed.stderr
            rows = {row["name"]: row["type"] for row in json.loads(listed.stdout)["services"]}
            assert rows == {
                "/robot1/dock": TRIGGER,
                "/robot1/jammed": TRIGGER,
                "/robot1/lamp": "std_srvs/srv/SetBool",
                "/robot1/slow": TRIGGER,
            }
            called = cli(tmp_path, "call", "/robot1/dock", TRIGGER, "{}", *where)
            assert called.returncode == 0, called.stderr
            assert "response:" in called.stdout and 'message: "docked"' in called.stdout
            assert "success: true" in called.stdout
            jammed = cli(tmp_path, "call", "/robot1/jammed", TRIGGER, *where)
            assert jammed.returncode == 1
            assert "ServiceFailed" in jammed.stderr
            assert "RuntimeError: the dock is blocked" in jammed.stderr
            # the CLI in this process: a typed request in YAML's flow style, and bad input
            capsys.readouterr()
            args = ["call", "/robot1/lamp", "std_srvs/srv/SetBool", "{data: true}", *where]
            assert service_main([*args, "--json"]) == 0
            answer = json.loads(capsys.readouterr().out)
            assert answer["response"] == {"success": True, "message": "lamp on"}
            assert answer["request"] == {"data": True}
            for bad, code, says in [
                (["/robot1/dok", TRIGGER], 2, "NoSuchService"),
                (["/robot1/lamp", "std_srvs/srv/SetBool", "{data: 3}"], 2, "`bool`"),
                (["/robot1/lamp", TRIGGER], 2, "ServiceTypeError"),
                (["/robot9/dock", TRIGGER, "--timeout", "2"], 1, "RobotGone"),
            ]:
                assert service_main(["call", *bad, *where]) == code, bad
                assert says in capsys.readouterr().err, bad
            # ServiceCaller on a client session of its own, the type from the announcement
            transport = ZenohTransport.open(
                SessionSettings(mode="client", connect=[endpoint]), timeout_s=5
            )
            try:
                caller = ServiceCaller(transport, FLEET, caller="test")
                wait_until(
                    lambda: caller.directory("robot1").services is not None,
                    timeout_s=5,
                    what="robot1's announcement",
                )
                docked = caller.call("robot1", "dock", {}, 5.0)
                assert (docked.success, docked.message) == (True, "docked")
                lamp = caller.call("robot1", "lamp", {"data": False}, 5.0)
                assert lamp.message == "lamp off"
                with pytest.raises(ServiceFailed, match="the dock is blocked"):
                    caller.call("robot1", "jammed", {}, 5.0)
                slow_started = time.monotonic()
                with pytest.raises(ServiceTimeout) as timeout:
                    caller.call("robot1", "slow", {}, 0.3)
                assert timeout.value.reached
                with pytest.raises(NoSuchService):
                    caller.call("robot1", "dok", {}, 5.0)
                with pytest.raises(RobotGone):
                    caller.call("robot9", "dock", {}, 2.0, type=TRIGGER)
                counted = caller.counters()["robot1"]
                assert (counted["dock"].calls, counted["dock"].ok) == (1, 1)
                assert (counted["slow"].calls, counted["slow"].timeouts) == (1, 1)
                assert counted["jammed"].failed == 1 and counted["dok"].unknown == 1
                caller.close()
            finally:
                transport.close()
            # the slow handler ends (late) before the robot's final report
            time.sleep(max(0.0, slow_started + SLOW_S + 0.3 - time.monotonic()))
            assert robot.interrupt() == 0
        assert server.interrupt() == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    side = {name: row["robot"] for name, row in summary["services"]["robot1"].items()}
    assert side["dock"]["calls"] == side["dock"]["ok"] == 2
    assert side["lamp"]["ok"] == 2 and side["lamp"]["failed"] == 0
    assert side["lamp"]["calls"] == 2 + side["lamp"]["type_errors"]
    assert side["jammed"]["calls"] == side["jammed"]["failed"] == 2
    assert side["jammed"]["last_error"] == "RuntimeError: the dock is blocked"
    assert side["slow"]["calls"] == side["slow"]["timeouts"] == 1
    assert side["slow"]["handler_ms_max"] >= SLOW_S * 1000
    assert all(row["caller"] is None for row in summary["services"]["robot1"].values())


def test_a_handler_that_cannot_be_made_stops_the_robot_with_exit_code_2(tmp_path: Path) -> None:
    with router() as (_router, endpoint):
        config = tmp_path / "robot.toml"
        config.write_text(
            f'robot_id = "robot1"\nfleet = "{FLEET}"\nconnect = ["{endpoint}"]\n'
            "match_timeout_s = 0.2\n[clock]\nenabled = false\n"
            '[[services]]\nname = "lamp"\ntype = "std_srvs/srv/SetBool"\n'
            'handler = "tests.integration.service_handlers:Lamp"\n'  # without its options
        )
        done = subprocess.run(
            [sys.executable, "-m", "arpz.robot", "--config", str(config)],
            cwd=tmp_path,
            env={**os.environ, **ENV},
            capture_output=True,
            text=True,
            timeout=60,
        )
    assert done.returncode == 2, done.stderr
    assert "services[lamp].handler: tests.integration.service_handlers:Lamp({}) raised" in (
        done.stderr
    )
    assert "KeyError('label')" in done.stderr
