"""``python -m arpz.tools.doctor`` against real fleets: a healthy one, one with a robot whose
clock is 0.5 s off, and an endpoint nobody listens on."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from tests.integration.fleet import ceddp, robots, write_robot
from tests.integration.secure_fleet import (
    client_config,
    make_fleet_tls,
    secure_ceddp,
    write_secure_robot,
)
from tests.support import free_port

pytestmark = pytest.mark.integration


def doctor(*args: str, timeout_s: float = 30) -> tuple[int, str, dict[str, Any], float]:
    """Run the doctor; returns its exit code, its text output, its JSON and how long it ran."""
    start = time.monotonic()
    done = subprocess.run(
        [sys.executable, "-m", "arpz.tools.doctor", *args, "--json", "-"],
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )
    elapsed = time.monotonic() - start
    text = subprocess.run(  # the same run as text: one line per check
        [sys.executable, "-m", "arpz.tools.doctor", *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )
    assert text.returncode == done.returncode, text.stdout + text.stderr
    return done.returncode, text.stdout, json.loads(done.stdout), elapsed


def _error_bound_ms(row: dict[str, Any]) -> float:
    """How far a robot's clock estimate may be from the truth: 5 ms, or half the round trip of
    the exchange it came from, beyond which a request/reply estimate cannot tell (on a loaded
    two-core host a best round trip of tens of ms happens: -486.5 ms for a 500 ms shift once)."""
    # the bound must not grow until anything passes: a best round trip this long is no estimate
    assert row["clock_delay_ms"] < 200, row
    return max(5.0, row["clock_delay_ms"] / 2)


def levels(report: dict[str, Any]) -> dict[str, str]:
    return {c["check"]: c["level"] for c in report["checks"]}


def test_doctor_on_a_healthy_fleet_and_on_one_with_a_shifted_clock(tmp_path: Path) -> None:
    with ceddp(tmp_path, extra="[clock]\nmax_offset_ms = 50\n") as (_, endpoint):
        configs = [
            write_robot(tmp_path, "robot1", endpoint, preset="machine1"),
            write_robot(tmp_path, "robot2", endpoint, preset="machine2"),
        ]
        with robots(tmp_path, configs):
            code, text, report, _ = doctor("--connect", endpoint, "--fleet", "itest")
            print(text)
            assert code == 0, text
            assert set(report["robots"]) == {"robot1", "robot2"}
            for robot, row in report["robots"].items():
                assert row["arpz_version"] and row["zenoh_version"], row
                assert abs(row["clock_offset_ms"]) <= _error_bound_ms(row), row
                assert f"OK   clock {robot}: offset " in text
            found = levels(report)
            for check in ("router", "ceddp", "robots", "versions", "qos", "delivery", "tls"):
                assert found[check] == "OK", text
            assert found["access control"] == "WARN"  # the test CEDDP runs without one
            assert "robot1, robot2 all run arpz" in text
            shifted = write_robot(
                tmp_path, "robot3", endpoint, preset="machine1", extra="[clock]\nshift_s = 0.5\n"
            )
            with robots(tmp_path, [shifted]):
                code, text, report, _ = doctor("--connect", endpoint, "--fleet", "itest")
                print(text)
    assert code == 1, text
    assert levels(report)["clock robot3"] == "FAIL"
    assert "FAIL clock robot3: offset -" in text and "exceeds the bound of 50 ms" in text
    shifted_row = report["robots"]["robot3"]
    assert abs(shifted_row["clock_offset_ms"] + 500) <= _error_bound_ms(shifted_row), shifted_row
    assert levels(report)["clock robot1"] == "OK"


def test_doctor_names_an_unreachable_endpoint_and_keeps_to_its_timeout() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    code, text, report, elapsed = doctor("--connect", endpoint, "--timeout", "2")
    print(text)
    assert code == 1
    assert report["checks"][0]["check"] == "router" and report["checks"][0]["level"] == "FAIL"
    assert endpoint in text and "2 s" in text
    assert elapsed < 2 + 3  # the timeout, plus starting Python and Zenoh


def test_doctor_refuses_bad_input_with_exit_2() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "arpz.tools.doctor", "--connect", "foo"],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert done.returncode == 2
    assert "arpz doctor: error: --connect" in done.stderr


def test_doctor_on_a_fleet_with_mutual_tls_and_access_control(tmp_path: Path) -> None:
    """With the deploy/ certificates and router config: the doctor, holding an observer's
    certificate, reads their expiry, sees access control in force, and every robot's clock
    exchange passes the access control (the robots may query ``ceddp/clock``)."""
    tls = make_fleet_tls(tmp_path / "tls", "sec", ["robot1"], observers=("doc",))
    with secure_ceddp(tmp_path, tls, fleet="sec") as (_, endpoint):
        config = write_secure_robot(
            tmp_path,
            "robot1",
            endpoint,
            client_config(tls, "robot1"),
            fleet="sec",
            preset="machine1",
        )
        with robots(tmp_path, [config]):
            code, text, report, _ = doctor(
                "--connect",
                endpoint,
                "--fleet",
                "sec",
                "--zenoh-config",
                str(client_config(tls, "doc")),
            )
            print(text)
    found = levels(report)
    assert code == 0, text
    assert found["access control"] == "OK" and found["tls"] == "OK", text
    assert found["tls root_ca_certificate"] == "OK" and found["tls connect_certificate"] == "OK"
    assert "the CEDDP reports TLS on" in text
    assert found["clock robot1"] == "OK", text
