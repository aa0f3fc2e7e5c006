"""characterise through a real Zenoh router: a client plays two robots and a CEDDP."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from arpz.configure.model import load_model
from arpz.core import keys
from arpz.core.messages import (
    Announce,
    CeddpStats,
    RobotStats,
    TopicCounters,
    TopicInfo,
    TopicRate,
    encode,
)
from tests.support import client, router

pytestmark = pytest.mark.integration

FLEET = "charfleet"


def _publish_fleet(endpoint: str, stop: threading.Event) -> None:
    with client(endpoint) as bus:
        sent = 0
        while not stop.is_set():
            sent += 1
            now = time.time_ns()
            for robot, cpu, rate in (("r1", 12.5, 10.0), ("r2", 30.0, 5.0)):
                bus.put(
                    keys.announce_key(FLEET, robot),
                    encode(
                        Announce(
                            robot=robot,
                            incarnation="x",
                            commands=[],
                            sensors=[
                                TopicInfo(
                                    topic="lidar", kind="lidar", rate_hz=rate, value_type="float"
                                )
                            ],
                        )
                    ),
                )
                bus.put(
                    keys.stats_key(FLEET, robot),
                    encode(
                        RobotStats(
                            robot=robot,
                            incarnation="x",
                            stamp_ns=now,
                            final=False,
                            cpu_percent=cpu,
                            topics={
                                "lidar": TopicCounters(
                                    sent=sent, bytes_sent=100 * sent, rate_hz=rate
                                )
                            },
                        )
                    ),
                )
            # the CEDDP receives r1 at its full rate and r2 at 80 % of it
            bus.put(
                keys.ceddp_stats_key(FLEET),
                encode(
                    CeddpStats(
                        stamp_ns=now,
                        cpu_percent=42.0,
                        topics=[
                            TopicRate(robot="r1", topic="lidar", rate_hz=10.0, bytes_per_s=500.0),
                            TopicRate(robot="r2", topic="lidar", rate_hz=4.0, bytes_per_s=200.0),
                        ],
                    )
                ),
            )
            stop.wait(0.1)


def characterise(
    endpoint: str, fleet: str, duration_s: float, out: Path | str
) -> subprocess.CompletedProcess[str]:
    """``python -m arpz.configure characterise`` as a user runs it."""
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "arpz.configure",
            "characterise",
            "--connect",
            endpoint,
            "--fleet",
            fleet,
            "--duration",
            str(duration_s),
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_characterise_builds_a_model_and_reports_eq10(tmp_path):
    out = tmp_path / "fleet.json"
    with router() as (_, endpoint):
        stop = threading.Event()
        publisher = threading.Thread(target=_publish_fleet, args=(endpoint, stop))
        publisher.start()
        try:
            proc = characterise(endpoint, FLEET, 1.5, str(out))
        finally:
            stop.set()
            publisher.join(timeout=10)
    assert proc.returncode == 0, proc.stderr
    model = load_model(out)
    assert {c.name for c in model.computers} == {"r1", "r2", "server"}
    nodes = {n.name: n for n in model.nodes}
    assert nodes["r1_agent"].settings[0].cpu == pytest.approx(12.5)
    assert nodes["r2_agent"].residence == ["r2"]
    assert nodes["ceddp"].settings[0].cpu == pytest.approx(42.0)
    bandwidth = {m.source: m.bandwidth for m in model.messages}
    assert bandwidth == {"r1_agent": pytest.approx(500.0), "r2_agent": pytest.approx(200.0)}
    # eq. 10: r2's lidar arrives at 4 Hz of the 5 Hz announced -> 80 % of its performance
    line = next(ln for ln in proc.stdout.splitlines() if ln.startswith("r2 "))
    assert line.split()[-2] == "80.00"
    # the characterised model is solvable as is
    solved = subprocess.run(
        [sys.executable, "-m", "arpz.configure", "solve", str(out), "--method", "exact", "--json"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert solved.returncode == 0, solved.stderr


def test_characterise_says_when_it_hears_nothing(tmp_path):
    with router() as (_, endpoint):
        proc = characterise(endpoint, "silent", 0.3, str(tmp_path / "m.json"))
    assert proc.returncode == 3
    assert "heard nothing" in proc.stderr
