"""Soak: a CEDDP and robots at a high rate for a while; memory and queues must stay flat.

A fleet runs for days, so anything that grows with time (a list nobody trims, a queue the CEDDP
cannot drain, a cache per message) eventually stops it. One run of ``ARPZ_SOAK_S`` seconds
(45 by default, so the suite stays within its CI budget; ``ARPZ_SOAK_S=600 python -m pytest
tests/integration/test_soak.py`` for
a real soak) samples every process's resident memory from /proc once a second; the tests then
judge the samples taken after a warm-up (imports, allocator pools, first dashboard chunks):

- the robots' memory is flat and the CEDDP keeps up (its arrival rate does not sag, latency
  stays low, so no queue is growing) and every count reconciles at the end;
- the CEDDP's memory grows no faster than its bounded latency buffers can explain.
"""

from __future__ import annotations

import json
import os
import statistics
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from arpz.core.messages import CEDDP_STATS_DECODER
from tests.integration.fleet import STEADY_MALLOC, ceddp, robots
from tests.integration.secure_fleet import rss_mb
from tests.support import client

SOAK_S = float(os.environ.get("ARPZ_SOAK_S", "45"))
#: pytest-timeout's limit for each test here. The first test carries the module fixture, which
#: runs the whole soak, so the suite's 300 s would kill a longer soak (ARPZ_SOAK_S=600) however
#: healthy. Start-up and shutdown are bounded by the waits in tests/integration/fleet.py (the
#: CEDDP and each robot up within 30 s, each robot down within 20 s, the CEDDP within 60 s:
#: 240 s at worst); 300 s on top of the soak covers them with room for a loaded machine.
TIMEOUT_S = SOAK_S + 300.0

# heavy or timing-bound: runs with the whole machine to itself (tests/conftest.py, cpu_share;
# its memory slope and reconciliation failed once with a unit test beside it)
pytestmark = [
    pytest.mark.integration,
    pytest.mark.slow,
    pytest.mark.timeout(TIMEOUT_S),
    pytest.mark.cpu_exclusive(whole_machine=True),
]

WARMUP_S = max(12.0, SOAK_S / 4)
ROBOTS = ("robot1", "robot2", "robot3")
RATE_HZ = 100.0
TOPICS_PER_ROBOT = 6  # machine1: lidar, light, flame, dht11, imu, pir
#: what the CEDDP may legitimately add per second: latency windows waiting for their fold into
#: the whole-run histograms (8 bytes a sample, up to 4 096 per topic), and the channel's bounded
#: FIFOs filling while a slow host lags. 0.1 held on this VM when it was fast; twice, when a
#: neighbour slowed it fourfold (raw Zenoh 240 000 samples/s against 940 000), it measured 0.142
#: and 0.144 with the same code that passed before. A leak shows over ARPZ_SOAK_S=600 at any limit.
CEDDP_MB_PER_S = 0.25
ROBOT_SPREAD_MB = 8.0


@dataclass
class SoakRun:
    """What one soak measured; the tests below judge it."""

    times: list[float] = field(default_factory=list)
    ceddp_mb: list[float] = field(default_factory=list)
    robot_mb: dict[str, list[float]] = field(default_factory=dict)
    #: (time since start, total samples per second arriving at the CEDDP) from its own reports
    rates: list[tuple[float, float]] = field(default_factory=list)
    #: (time since start, the interval's pooled p99 latency, ms) from the same reports
    latencies: list[tuple[float, float]] = field(default_factory=list)
    summary: dict[str, Any] = field(default_factory=dict)
    rrd_bytes: int = 0

    def after_warmup(self, values: list[float]) -> tuple[list[float], list[float]]:
        pairs = [(t, v) for t, v in zip(self.times, values, strict=True) if t >= WARMUP_S]
        return [t for t, _ in pairs], [v for _, v in pairs]


def _slope(xs: list[float], ys: list[float]) -> float:
    """Least-squares growth per second: robust to the allocator's occasional steps."""
    n = len(xs)
    mx, my = sum(xs) / n, sum(ys) / n
    var = sum((x - mx) ** 2 for x in xs)
    return sum((x - mx) * (y - my) for x, y in zip(xs, ys, strict=True)) / var


def _robot_config(tmp: Path, robot: str, endpoint: str) -> Path:
    """Every reading sent (no local cache): the most traffic a machine1 robot makes."""
    path = tmp / f"{robot}.toml"
    path.write_text(
        f'robot_id = "{robot}"\nfleet = "itest"\nconnect = ["{endpoint}"]\n'
        f'preset = "machine1"\npreset_rate_hz = {RATE_HZ}\nstats_period_s = 0.5\n'
        "[local_cache]\nenabled = false\n"
    )
    return path


@pytest.fixture(scope="module")
def soak(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SoakRun]:
    tmp = tmp_path_factory.mktemp("soak")
    run = SoakRun(robot_mb={robot: [] for robot in ROBOTS})
    lock = threading.Lock()
    start = time.monotonic()

    def on_stats(_key: str, payload: bytes, _att: bytes | None) -> None:
        stats = CEDDP_STATS_DECODER.decode(payload)
        with lock:
            at = time.monotonic() - start
            run.rates.append((at, sum(t.rate_hz for t in stats.topics)))
            if stats.latency_ms_p99 is not None:
                run.latencies.append((at, stats.latency_ms_p99))

    with ceddp(tmp, env=STEADY_MALLOC) as (server, endpoint):
        configs = [_robot_config(tmp, robot, endpoint) for robot in ROBOTS]
        with robots(tmp, configs) as procs, client(endpoint) as raw:
            raw.subscribe("arpz/itest/ceddp/stats", on_stats)
            start = time.monotonic()
            while (now := time.monotonic() - start) < SOAK_S:
                for proc in (server, *procs):
                    assert proc.popen.poll() is None, f"{proc.name} died:\n{proc.output()}"
                run.times.append(now)
                run.ceddp_mb.append(rss_mb(server.popen.pid))
                for robot, proc in zip(ROBOTS, procs, strict=True):
                    run.robot_mb[robot].append(rss_mb(proc.popen.pid))
                time.sleep(max(0.0, 1.0 - (time.monotonic() - start - now)))
            for proc in procs:
                assert proc.interrupt() == 0, proc.output()
        assert server.interrupt(timeout_s=60) == 0, server.output()
    run.summary = json.loads((tmp / "summary.json").read_text())
    run.rrd_bytes = (tmp / "ceddp.rrd").stat().st_size
    print(
        f"\nsoak {SOAK_S:.0f} s: CEDDP RSS {run.ceddp_mb[0]:.0f} -> {run.ceddp_mb[-1]:.0f} MB, "
        f"robots {[round(v[-1]) for v in run.robot_mb.values()]} MB, "
        f".rrd {run.rrd_bytes / 1e6:.0f} MB"
    )
    yield run


def test_counts_reconcile_robots_stay_flat_and_the_ceddp_keeps_up(soak: SoakRun) -> None:
    summary = soak.summary
    for robot in ROBOTS:
        record = summary["robots"][robot]
        assert record["final_stats"], robot
        assert len(record["topics"]) == TOPICS_PER_ROBOT, sorted(record["topics"])
        for topic, t in record["topics"].items():
            assert t["produced"] == t["sent"] + t["held_back"] > 0, (robot, topic, t)
            # nothing silent: what did not arrive was declared lost. On loopback a sample is lost
            # only when the writer's KEEP_LAST history overwrote it before the CEDDP acknowledged
            # it, which the writer counts (a slowed host, 260 ms p99, lost 1-10 of about 4 100
            # per topic this way, each overwrite reported); so every loss must be one of those
            assert t["received"] + t["lost"] == t["sent"], (robot, topic, t)
            assert t["lost"] <= t["overwritten_unacked"], (robot, topic, t)
            assert t["lost"] <= 0.01 * t["sent"], (robot, topic, t)
            assert t["decode_errors"] == 0, (robot, topic, t)
        # a CEDDP falling behind would show as latency growing with the backlog (to seconds
        # within a minute); the bounds leave room for a loaded CI machine's scheduling spikes
        latency = (record["latency_ms_p50"], record["latency_ms_p99"])
        assert latency[0] < 250 and latency[1] < 2000, (robot, latency)
        # nothing held the robots back for long (backpressure from a slow CEDDP would)
        produced = sum(t["produced"] for t in record["topics"].values())
        assert produced > 0.6 * TOPICS_PER_ROBOT * RATE_HZ * SOAK_S, (robot, produced)
    for robot, values in soak.robot_mb.items():
        _, after = soak.after_warmup(values)
        assert max(after) - min(after) < ROBOT_SPREAD_MB, (robot, values)
    # what arrives per second at the end is what arrived after the warm-up: no queue builds up
    rates = [r for t, r in soak.rates if t >= WARMUP_S]
    assert len(rates) >= 10, soak.rates
    third = len(rates) // 3
    early, late = sum(rates[:third]) / third, sum(rates[-third:]) / third
    # (the robots' Python schedulers may run below the nominal rate on a loaded machine: that is
    # measured above; here only the trend matters)
    offered = len(ROBOTS) * TOPICS_PER_ROBOT * RATE_HZ
    assert late > 0.5 * offered, (offered, early, late)
    if late <= 0.85 * early:
        # fewer arrivals late: a CEDDP falling behind, or robots sending less on a host that
        # slowed down mid-run (CI saw 0.84 of early once). A queue building up behind a slow
        # CEDDP delays every sample in it, so its latency grows; robots that send less do not
        # delay what they send. Tell them apart by the CEDDP's own latency reports.
        waits = [v for t, v in soak.latencies if t >= WARMUP_S]
        assert len(waits) >= 3, soak.latencies
        third_lat = len(waits) // 3
        early_p99 = statistics.median(waits[:third_lat])
        late_p99 = statistics.median(waits[-third_lat:])
        assert late_p99 < max(50.0, 2 * early_p99), (early, late, early_p99, late_p99, waits)


def test_the_ceddp_memory_stays_flat_after_warmup(soak: SoakRun) -> None:
    times, values = soak.after_warmup(soak.ceddp_mb)
    assert len(times) >= 10, soak.times
    growth = _slope(times, values)
    assert growth < CEDDP_MB_PER_S, (
        f"CEDDP RSS grows {growth:.3f} MB/s after warm-up (limit {CEDDP_MB_PER_S}): "
        f"{[round(v) for v in soak.ceddp_mb]}"
    )


def test_the_recording_grows_by_kilobytes_per_topic_not_megabytes(soak: SoakRun) -> None:
    """A week-long run must fit on the server's disk: the dashboard's few metrics per topic
    every metrics period should cost tens of bytes each, not a kilobyte."""
    topics = len(ROBOTS) * TOPICS_PER_ROBOT
    per_topic = soak.rrd_bytes / SOAK_S / topics
    assert per_topic < 5_000, f"{per_topic / 1e3:.1f} kB/s per topic ({soak.rrd_bytes} bytes)"
