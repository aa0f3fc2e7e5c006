"""``python -m arpz.perf fleet`` as a real process: a small fleet of real robot agents in two
worker processes against a real CEDDP process; the files it writes, and no process left behind."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from arpz.perf.harness import free_port, perf_router, pubsub

# heavy or timing-bound: runs with the cores to itself (tests/conftest.py, cpu_share)
pytestmark = [pytest.mark.integration, pytest.mark.cpu_exclusive]


def _gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    # a zombie is gone too: it runs nothing (its parent, the tool, has exited)
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return True


@pytest.mark.parametrize(
    ("robot_threads", "robot_sched", "scheduling"),
    [("shared", "batch", "SCHED_BATCH, nice 10"), ("own", "normal", "SCHED_OTHER, nice 10")],
)
def test_fleet_load_reports_every_robot_reconciled_and_ends_its_processes(
    tmp_path: Path, robot_threads: str, robot_sched: str, scheduling: str
) -> None:
    """Either way a worker runs its robots (one thread for all, the default; a thread each),
    under either scheduling policy, which the report shows as the robots' thread read it."""
    out_json, out_csv = tmp_path / "fleet.json", tmp_path / "fleet.csv"
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "arpz.perf",
            "fleet",
            "--robots",
            "6",
            "--processes",
            "2",
            "--topics",
            "2",
            "--rate",
            "20",
            "--duration",
            "4",
            "--robot-threads",
            robot_threads,
            "--robot-sched",
            robot_sched,
            "--workdir",
            str(tmp_path / "work"),
            "--json",
            str(out_json),
            "--csv",
            str(out_csv),
        ],
        capture_output=True,
        text=True,
        timeout=90,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    assert "reconciled: sent == delivered + lost for all 6 robots" in run.stdout
    doc = json.loads(out_json.read_text())
    robots = {r["robot"]: r for r in doc["robots"]}
    assert sorted(robots) == [f"c0-r{i:03d}" for i in range(1, 7)]
    for row in robots.values():
        assert row["final_report"] and row["reconciled"], row
        assert row["sent"] == row["delivered"] + row["lost"]
        assert row["worker_sent"] == row["sent"]
        assert row["sent"] > 0 and row["latency_ms_p99"] is not None
    fleet = doc["fleet"]
    assert fleet["reconciled"] and fleet["failures"] == []
    assert fleet["workers_scheduling"] == scheduling
    assert f"robot workers {fleet['workers_cpu_cores']:.2f} cores ({scheduling})" in run.stdout
    assert fleet["delivered"] == sum(r["delivered"] for r in robots.values())
    # the hypervisor's share, whole window and worst second, and the flag the report derives
    stolen, stolen_peak = fleet["host_steal_cores"], fleet["host_steal_cores_peak"]
    assert 0.0 <= stolen <= stolen_peak < 2.0, fleet
    assert fleet["steal_flagged"] is (stolen >= 0.01)
    assert ("STOLEN: the hypervisor took" in run.stdout) is fleet["steal_flagged"]
    # 6 robots x 2 topics x 20 Hz for about 4 s, on a shared host: most of it, never more
    assert 0.5 * 960 <= fleet["sent"] <= 1.2 * 960
    (ceddp,) = doc["ceddps"]
    process = ceddp["process"]
    assert 0.0 < process["cpu_cores"] < 2.0
    assert 30 < process["rss_peak_mb"] < 2000
    assert process["rss_mb"] <= process["rss_peak_mb"]
    # the CEDDP's ingest backlog in time, from its own reports or its summary (ms)
    assert 0.0 <= ceddp["ingest_backlog_ms_max"] < 10_000, ceddp
    # its p99 over the whole run's pulls (summary.json; the max above is the load window's,
    # rounded to the microsecond in the CEDDP's reports: the two are not bounded by each other)
    p99 = ceddp["ingest_backlog_ms_p99"]
    assert p99 is None or 0.0 <= p99 < 10_000, ceddp
    assert "ingest_backlog" not in doc["unavailable"], doc["unavailable"]
    # every sample's time inside the CEDDP, router to processed (summary.json, upper bounds)
    sojourn_p99, sojourn_max = ceddp["sojourn_ms_p99"], ceddp["sojourn_ms_max"]
    assert sojourn_p99 is not None and sojourn_max is not None, ceddp
    assert 0.0 < sojourn_p99 <= sojourn_max * 1.01 < 10_000, ceddp
    with out_csv.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert sorted(r["robot"] for r in rows) == sorted(robots)
    assert all(r["reconciled"] == "True" for r in rows)
    assert len(doc["pids"]) == 3  # one CEDDP, two workers
    assert all(_gone(pid) for pid in doc["pids"]), doc["pids"]


def test_zenoh_config_file_applies_to_router_pub_and_sub(tmp_path: Path) -> None:
    """Shared memory off in every session (the large-message benchmarks' setting): the samples
    still all arrive, and every process accepted the file."""
    config = tmp_path / "noshm.json5"
    config.write_text("{ transport: { shared_memory: { enabled: false } } }\n")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with perf_router(endpoint, zenoh_config=str(config)):
        pub, report = pubsub(
            transport="arpz",
            pub_connect=endpoint,
            sub_connect=endpoint,
            count=500,
            rate_hz=2000,
            size=4096,
            extra=("--zenoh-config", str(config)),
        )
    assert pub["sent"] == 500
    assert (report["received"], report["lost"], report["unaccounted"]) == (500, 0, 0)
