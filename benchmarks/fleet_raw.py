"""A small fleet through arpz against the same fleet on raw Zenoh, in one run.

arpz: ``python -m arpz.perf fleet`` (``arpz.perf.fleet.run_load``): N real robot agents (local
cache off, RELIABLE KEEP_ALL, bundled) in P worker processes (nice 10, ``SCHED_BATCH``) against a
real CEDDP process. Raw Zenoh: the same shape with nothing of arpz in the path: N robots x T
topics x R Hz of 60-byte samples (about a robot's typed sample), packed into the same P worker
processes (nice 10, ``SCHED_BATCH``, one thread sending every robot's tick at its own phase, a
declared publisher a topic, congestion control BLOCK), into a router session in its own process
whose subscriber callback only takes the arrival time (the cheapest a Python subscriber can be).
Latency: source stamp to arrival (one host, one clock); a robot's p99, then the median robot's
and the worst robot's. CPU a sample: the receiving process's CPU (all its threads) over the
window, per delivered sample. Rounds alternate arpz and raw; the ratios are arpz / raw, the
median of the rounds' own ratios.

    python benchmarks/fleet_raw.py [--robots 10] [--topics 8] [--rate 100] [--processes 2]
        [--duration 10] [--rounds 1]

The subscriber and the workers are this module run again (``sub`` and ``worker``).
"""

from __future__ import annotations

import argparse
import heapq
import json
import os
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from array import array
from collections.abc import Callable
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from arpz.core.transport import SessionSettings
from arpz.perf.zenoh_baselines import ZenohPub, ZenohSub, open_session
from arpz.tools.launch import free_port

if TYPE_CHECKING:  # the workers and the subscriber need none of arpz's fleet
    from arpz.perf.fleet_report import FleetPoint

#: progress lines, printed as they come
SAY = partial(print, flush=True)

#: a sample: its send time (ns since the epoch) and its robot, padded to SAMPLE_BYTES
HEAD = struct.Struct("!qH")
SAMPLE_BYTES = 60
KEYS = "bench/fleet"
ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class RawFleet:
    """The raw Zenoh fleet's figures, named as ``perf fleet`` names them."""

    offered: int
    sent: int
    delivered: int
    delivered_ratio: float
    latency_ms_p50: float
    latency_ms_p99: float
    latency_ms_p99_median_robot: float
    cpu_cores: float
    cpu_us_per_sample: float


# ------------------------------------------------------------------------------ the processes
def serve(endpoint: str, robots: int) -> None:
    """The receiving side (``sub``): a router session with a subscriber on every robot's keys.
    stdin "go" starts the window, "stop" ends it and prints the figures as one JSON line."""
    latencies = [array("q") for _ in range(robots)]
    session = open_session(SessionSettings(mode="router", listen=[endpoint]))

    def on_payload(payload: bytes) -> None:
        now = time.time_ns()
        stamp, robot = HEAD.unpack_from(payload)
        latencies[robot].append(now - stamp)

    sub = ZenohSub(session, f"{KEYS}/**", on_payload)
    print("ready", flush=True)
    sys.stdin.readline()
    for values in latencies:
        del values[:]
    cpu0, wall0 = time.process_time(), time.monotonic()
    sys.stdin.readline()
    cpu_s, wall_s = time.process_time() - cpu0, time.monotonic() - wall0
    per_robot = [np.frombuffer(values, dtype=np.int64) / 1e6 for values in latencies]
    sub.close()
    p99 = [float(np.percentile(ms, 99)) if len(ms) else float("nan") for ms in per_robot]
    every = np.concatenate(per_robot)
    doc = {
        "delivered": len(every),
        "p50": float(np.percentile(every, 50)) if len(every) else float("nan"),
        "p99_robots": p99,
        "cpu_s": cpu_s,
        "wall_s": wall_s,
    }
    print(json.dumps(doc), flush=True)


def work(
    endpoint: str, robots: list[int], total: int, topics: int, rate_hz: float, duration_s: float
) -> None:
    """One worker (``worker``): its robots' ticks on one thread, each robot at its own phase of
    the period (robot i of ``total`` at i / total of it), as ``perf fleet`` spreads them; a tick
    more than a period late is skipped, as a robot skips a sensing period. Starts at stdin's
    "go"; prints the samples each robot sent."""
    os.nice(10)
    os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
    session = open_session(SessionSettings(mode="client", connect=[endpoint]))
    pubs = {
        robot: [ZenohPub(session, f"{KEYS}/r{robot}/t{t}", False) for t in range(topics)]
        for robot in robots
    }
    for robot_pubs in pubs.values():
        for pub in robot_pubs:
            pub.wait_matched(10)
    pad = bytes(SAMPLE_BYTES - HEAD.size)
    sent = dict.fromkeys(robots, 0)
    print("ready", flush=True)
    sys.stdin.readline()
    period = 1.0 / rate_hz
    start = time.monotonic()
    end = start + duration_s
    due = [(start + period * robot / total, robot) for robot in robots]
    heapq.heapify(due)
    while due[0][0] < end:
        at, robot = heapq.heappop(due)
        now = time.monotonic()
        if now < at:
            time.sleep(at - now)
        if time.monotonic() - at < period:
            for pub in pubs[robot]:
                pub.put(HEAD.pack(time.time_ns(), robot) + pad)
            sent[robot] += topics
        heapq.heappush(due, (at + period, robot))
    for robot_pubs in pubs.values():
        for pub in robot_pubs:
            pub.pub.undeclare()
    session.close()  # type: ignore[no-untyped-call]
    print(json.dumps({"sent": sent}), flush=True)


def _start(*args: str) -> subprocess.Popen[str]:
    # as a module of this checkout, with this checkout's arpz (not an installed one)
    proc = subprocess.Popen(
        [sys.executable, "-m", "benchmarks.fleet_raw", *args],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if line.strip() != "ready":
        proc.kill()
        raise RuntimeError(f"fleet_raw {args[0]} did not start: {line!r}")
    return proc


def _say(proc: subprocess.Popen[str], line: str) -> None:
    assert proc.stdin is not None
    proc.stdin.write(line + "\n")
    proc.stdin.flush()


def _result(proc: subprocess.Popen[str], timeout_s: float) -> dict[str, Any]:
    out, _ = proc.communicate(timeout=timeout_s)
    doc: dict[str, Any] = json.loads(out.strip().splitlines()[-1])
    return doc


def run_raw(
    robots: int, topics: int, rate_hz: float, processes: int, duration_s: float
) -> RawFleet:
    """The raw Zenoh fleet, every process ended on every exit path."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs: list[subprocess.Popen[str]] = []
    try:
        sub = _start("sub", endpoint, str(robots))
        procs.append(sub)
        shares = [list(range(robots))[w::processes] for w in range(processes)]
        for share in shares:
            spec = ",".join(map(str, share))
            flags = [str(robots), str(topics), str(rate_hz), str(duration_s)]
            procs.append(_start("worker", endpoint, spec, *flags))
        for proc in procs:
            _say(proc, "go")
        sent = sum(sum(_result(w, duration_s + 30)["sent"].values()) for w in procs[1:])
        time.sleep(0.5)  # what is still on its way
        _say(sub, "stop")
        doc = _result(sub, 30)
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    p99 = [value for value in doc["p99_robots"] if value == value]
    delivered = int(doc["delivered"])
    offered = round(robots * topics * rate_hz * duration_s)
    return RawFleet(
        offered=offered,
        sent=sent,
        delivered=delivered,
        delivered_ratio=delivered / offered,
        latency_ms_p50=doc["p50"],
        latency_ms_p99=max(p99, default=float("nan")),
        latency_ms_p99_median_robot=statistics.median(p99) if p99 else float("nan"),
        cpu_cores=doc["cpu_s"] / doc["wall_s"],
        cpu_us_per_sample=doc["cpu_s"] / max(delivered, 1) * 1e6,
    )


# ------------------------------------------------------------------------------ the comparison
def run_arpz(
    robots: int, topics: int, rate_hz: float, processes: int, duration_s: float, workdir: Path
) -> FleetPoint:
    from arpz.perf.fleet import FleetOptions, run_load

    options = FleetOptions(
        robots=robots, topics=topics, rate_hz=rate_hz, processes=processes, duration_s=duration_s
    )
    return run_load(options, workdir, progress=None).point


#: (name, arpz's figure, raw's figure): the ratios arpz / raw
Figure = tuple[str, Callable[["FleetPoint"], float | None], Callable[[RawFleet], float]]
RATIOS: tuple[Figure, ...] = (
    (
        "p99, median robot",
        lambda p: p.latency_ms_p99_median_robot,
        lambda r: r.latency_ms_p99_median_robot,
    ),
    ("p99, worst robot", lambda p: p.latency_ms_p99, lambda r: r.latency_ms_p99),
    ("CPU a sample", lambda p: p.ceddp_cpu_us_per_sample, lambda r: r.cpu_us_per_sample),
    ("delivered", lambda p: p.delivered_ratio, lambda r: r.delivered_ratio),
)


def measure(
    robots: int,
    topics: int,
    rate_hz: float,
    processes: int,
    duration_s: float,
    rounds: int,
    log: Callable[[str], object] = SAY,
) -> list[tuple[FleetPoint, RawFleet]]:
    """Rounds of arpz then raw Zenoh; each round's pair."""
    pairs = []
    with tempfile.TemporaryDirectory(prefix="fleet-raw-") as tmp:
        for round_ in range(1, rounds + 1):
            shape = (robots, topics, rate_hz, processes, duration_s)
            point = run_arpz(*shape, Path(tmp) / f"arpz{round_}")
            raw = run_raw(*shape)
            log(
                f"  round {round_}/{rounds}: arpz delivered {point.delivered_ratio:.3f} of "
                f"offered, p99 median robot {point.latency_ms_p99_median_robot:.2f} ms, worst "
                f"{point.latency_ms_p99:.2f} ms, CEDDP {point.ceddp_cpu_us_per_sample} us a "
                f"sample, lost {point.lost}; raw delivered {raw.delivered_ratio:.3f}, p99 "
                f"median robot {raw.latency_ms_p99_median_robot:.2f} ms, worst "
                f"{raw.latency_ms_p99:.2f} ms, subscriber {raw.cpu_us_per_sample:.1f} us a sample"
            )
            pairs.append((point, raw))
    return pairs


def ratios(pairs: list[tuple[FleetPoint, RawFleet]]) -> dict[str, float]:
    """arpz / raw of each figure: the median of the rounds' own ratios."""
    out = {}
    for name, ours, theirs in RATIOS:
        values = [a / b for a, b in ((ours(p), theirs(r)) for p, r in pairs) if a is not None and b]
        if values:
            out[name] = statistics.median(values)
    return out


def main() -> int:
    if sys.argv[1:2] == ["sub"]:
        serve(sys.argv[2], int(sys.argv[3]))
        return 0
    if sys.argv[1:2] == ["worker"]:
        endpoint, share, total, topics, rate, duration = sys.argv[2:8]
        robots = [int(r) for r in share.split(",") if r]
        work(endpoint, robots, int(total), int(topics), float(rate), float(duration))
        return 0
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--robots", type=int, default=10)
    ap.add_argument("--topics", type=int, default=8)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--processes", type=int, default=2)
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--rounds", type=int, default=1)
    args = ap.parse_args()
    pairs = measure(args.robots, args.topics, args.rate, args.processes, args.duration, args.rounds)
    for _, raw in pairs:
        SAY(f"  raw: {json.dumps(asdict(raw))}")
    print()
    print("| figure | arpz / raw Zenoh (median of the rounds) |")
    print("|---|---:|")
    for name, value in ratios(pairs).items():
        print(f"| {name} | {value:.2f}x |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
