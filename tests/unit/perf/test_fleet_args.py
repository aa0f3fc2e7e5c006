"""The fleet load test's arguments and plan: refused before any process starts (exit code 2)."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from types import SimpleNamespace

import pytest

from arpz.core.config import CeddpConfig, RobotConfig, from_dict
from arpz.perf import fleet
from arpz.perf.__main__ import main
from arpz.perf.fleet import (
    FleetArgumentError,
    FleetOptions,
    ceddp_configs,
    check_options,
    host_cpu_seconds,
    parse_sweep,
    placement,
    robot_phases,
    worker_plan,
)
from arpz.perf.fleet_watch import ceddp_of


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"robots": 0}, "--robots must be >= 1"),
        ({"topics": 65}, "--topics must be 1..64"),
        ({"rate_hz": 0.0}, "--rate must be in (0, 10000]"),
        ({"processes": 0}, "--processes must be >= 1"),
        ({"duration_s": -1.0}, "--duration must be > 0"),
        ({"ceddps": 3, "robots": 2}, "--ceddps 3 > --robots 2"),
        ({"depth": 0}, "--depth must be >= 1"),
        ({"robot_nice": 20}, "--robot-nice must be 0..19"),
        ({"robot_threads": "many"}, "--robot-threads must be one of shared, own"),
        ({"robot_phases": "random"}, "--robot-phases must be one of spread, aligned"),
        ({"robot_sched": "fifo"}, "--robot-sched must be one of normal, batch"),
        ({"heartbeat_ms": 0.0}, "--heartbeat-ms must be > 0"),
        ({"heartbeat_backoff": 0}, "--heartbeat-backoff must be 1..64"),
        ({"heartbeat_backoff": 65}, "--heartbeat-backoff must be 1..64"),
        ({"zenoh_config": "/nonexistent.json5"}, "no such file"),
    ],
)
def test_bad_options_are_refused(change: dict[str, object], message: str) -> None:
    with pytest.raises(FleetArgumentError, match=message.replace("(", r"\(").replace("]", r"\]")):
        check_options(dataclasses.replace(FleetOptions(), **change))  # type: ignore[arg-type]


def test_sweep_lists() -> None:
    assert parse_sweep("1,5,10,25") == [1, 5, 10, 25]
    for bad in ("", "5,1", "1,1", "0,2", "a,b"):
        with pytest.raises(FleetArgumentError, match="--sweep"):
            parse_sweep(bad)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["fleet", "--robots", "0"], "--robots must be >= 1"),
        (["fleet", "--size", "1024"], "--size: the robot agent sends"),
        (["fleet", "--png", "x.png"], "--png draws the scaling curve: give --sweep too"),
        (["fleet", "--sweep", "10,5"], "--sweep wants ascending"),
        (["fleet", "--zenoh-config", "/nonexistent.json5"], "no such file"),
        (["sub", "--connect", "tcp/127.0.0.1:1", "--zenoh-config", "/nonexistent"], "no such"),
    ],
)
def test_the_command_exits_2_with_the_reason(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_placement_spreads_robots_over_ceddps_and_workers() -> None:
    where = placement(FleetOptions(robots=5, processes=2, ceddps=2))
    assert where == {
        "c0-r001": (0, 0),
        "c1-r001": (1, 1),
        "c0-r002": (0, 0),
        "c1-r002": (1, 1),
        "c0-r003": (0, 0),
    }
    assert set(placement(FleetOptions(robots=2, processes=4)).values()) == {(0, 0), (0, 1)}


def test_the_plan_is_configs_the_ceddp_and_the_robots_accept(tmp_path: Path) -> None:
    options = FleetOptions(robots=3, topics=9, processes=2, ceddps=2, history="keep_last", depth=7)
    endpoints = ["tcp/127.0.0.1:7001", "tcp/127.0.0.1:7002"]
    ceddps = ceddp_configs(options, endpoints, tmp_path)
    assert [c["partition"] for c in ceddps] == ["c0-$*", "c1-$*"]
    assert "connect" not in ceddps[0] and ceddps[1]["connect"] == [endpoints[0]]
    plan, where = worker_plan(options, endpoints, tmp_path)
    robots = [
        from_dict(raw, RobotConfig, source="t") for worker in plan["workers"] for raw in worker
    ]
    assert sorted(r.robot_id for r in robots) == sorted(where)
    for robot in robots:
        assert len(robot.sensors) == 9 and not robot.local_cache.enabled
        assert robot.connect == [endpoints[where[robot.robot_id][0]]]
        assert robot.sensor_qos.depth == 7
        assert robot.sensor_qos.piggyback_heartbeats and robot.sensor_qos.heartbeat_backoff == 8
    ceddp = from_dict(ceddps[0], CeddpConfig, source="t")
    assert ceddp.sensor_qos == robots[0].sensor_qos
    assert plan["nice"] == 10 and plan["sched"] == "batch"


def test_a_self_report_is_attributed_by_its_robots() -> None:
    @dataclasses.dataclass
    class Rate:
        robot: str

    assert ceddp_of([Rate("c1-r004")]) == 1
    assert ceddp_of([Rate("robot1"), Rate("c0-r001")]) == 0
    assert ceddp_of([]) is None


def test_robot_phases_spread_the_fleet_over_each_job_s_period() -> None:
    robots = [f"r{i}" for i in range(4)]
    spread = robot_phases(FleetOptions(robots=4), robots)
    assert spread == {"r0": 0.0, "r1": 0.25, "r2": 0.5, "r3": 0.75}
    aligned = robot_phases(FleetOptions(robots=4, robot_phases="aligned"), robots)
    assert set(aligned.values()) == {0.0}


def test_host_cpu_reads_busy_total_and_stolen_ticks_of_proc_stat() -> None:
    # user nice system idle iowait irq softirq steal guest guest_nice, in clock ticks
    line = "cpu  500 0 200 1000 100 0 40 60 0 0"
    busy, total, stolen = host_cpu_seconds(line)
    ticks = os.sysconf("SC_CLK_TCK")
    assert busy == pytest.approx(800 / ticks)  # idle and iowait left out, steal counted
    assert total == pytest.approx(1900 / ticks)
    assert stolen == pytest.approx(60 / ticks)
    assert host_cpu_seconds("cpu 1 2 3 4")[2] == 0.0  # an old kernel without the steal column


def test_the_sampler_keeps_the_worst_second_of_stolen_cpu(monkeypatch: pytest.MonkeyPatch) -> None:
    # (monotonic s, stolen s since boot): 0.2 s stolen in the second second, none after
    clock = iter([0.0, 1.0, 2.0, 2.5, 3.0, 4.0])
    stolen = iter([0.0, 0.0, 0.2, 0.2, 0.2, 0.2])
    # the module's own clock only: time.monotonic stays the pytest runner's
    monkeypatch.setattr(fleet, "time", SimpleNamespace(monotonic=lambda: next(clock)))
    monkeypatch.setattr(fleet, "host_busy_s", lambda: (0.0, 0.0, next(stolen)))
    sampler = fleet.ProcSampler([])
    for _ in range(5):
        sampler.sample()
    assert sampler.host_steal_cores() == pytest.approx(0.05)  # 0.2 s over 4 s
    assert sampler.host_steal_cores_peak() == pytest.approx(0.2)  # all in one second
