"""How long the CEDDP's periodic summary holds the ingest lock, with full latency reservoirs.

The CEDDP persists its summary every ``summary_period_s`` (5 s). Each robot's row holds p50 and
p99 of every topic's latency and staleness over the whole run, from reservoirs of bounded size;
ingest waits while a row is computed under the ingest lock, which shows as a latency tail. This
fills the reservoirs of N robots x T topics and times ``robot_summary`` per robot, for today's
reservoirs and for the reservoirs of 100 000 values arpz had before (one quantile call per
figure then, and the lock held for the whole fleet at once), in one run; and today's lock hold
with the percentiles deferred until the lock is released (``defer=True``, what the server does
since issue 17's fleet runs traced their p99 to this hold) against computed under it.

    python benchmarks/summary_stall.py [--robots 10] [--topics 8] [--rounds 3]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections import deque
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from arpz.ceddp.cache_control import CacheControl
from arpz.ceddp.control import RobotRecord
from arpz.ceddp.ingest import Ingest
from arpz.ceddp.planner import Planner
from arpz.ceddp.summary import resolve, robot_summary
from arpz.messages import Sample, encode
from arpz.percentiles import DEFAULT_CAPACITY, Distribution


def filled_ingest(robots: int, topics: int, capacity: int) -> Ingest:
    ingest = Ingest("f", Planner(), CacheControl(enabled=True))
    rng = np.random.default_rng(1)
    for r in range(robots):
        for t in range(topics):
            key = f"arpz/f/robot/r{r}/sensor/t{t}"
            ingest.handle_sensor(key, encode(Sample(f"r{r}:a", 1, 1, 1.0)), 2)
            m = ingest.topics[(f"r{r}", f"t{t}")]
            m.latency_ms, m.staleness_ms = Distribution(capacity), Distribution(capacity)
            for dist in (m.latency_ms, m.staleness_ms):
                for _ in range(2):  # more than the capacity: the reservoir is full
                    deque(map(dist.add, rng.random(capacity).tolist()), maxlen=0)
                    dist.take_window()
    return ingest


def old_style_row(ingest: Ingest, robot: str) -> None:
    """What a row cost before: one percentile call per figure (4 a topic, 3 pooled a robot)."""
    mine = [m for (r, _), m in ingest.topics.items() if r == robot]
    for m in mine:
        for dist in (m.latency_ms, m.staleness_ms):
            dist.quantile(50)
            dist.quantile(99)
    for q in (50, 99):
        np.percentile(np.concatenate([m.latency_ms.values() for m in mine]), q)
    np.percentile(np.concatenate([m.staleness_ms.values() for m in mine]), 99)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=10)
    ap.add_argument("--topics", type=int, default=8)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    print(f"filling {args.robots} x {args.topics} topics' reservoirs ...", flush=True)
    now = filled_ingest(args.robots, args.topics, DEFAULT_CAPACITY)
    before = filled_ingest(args.robots, args.topics, 100_000)
    names = [f"r{r}" for r in range(args.robots)]
    old_totals, new_totals, new_worst, deferred_worst = [], [], [], []
    for round_ in range(1, args.rounds + 1):
        t0 = time.perf_counter()
        for robot in names:
            old_style_row(before, robot)
        old_totals.append(time.perf_counter() - t0)
        per_robot = []
        for robot in names:
            t1 = time.perf_counter()
            robot_summary(now, robot, RobotRecord().as_report())
            per_robot.append(time.perf_counter() - t1)
        new_totals.append(sum(per_robot))
        new_worst.append(max(per_robot))
        held = []
        for robot in names:
            t1 = time.perf_counter()
            row = robot_summary(now, robot, RobotRecord().as_report(), defer=True)
            held.append(time.perf_counter() - t1)
            resolve(row)  # the percentiles, after the lock
        deferred_worst.append(max(held))
        print(
            f"round {round_}: before {old_totals[-1] * 1e3:.0f} ms under one lock; now "
            f"{new_totals[-1] * 1e3:.0f} ms in all, the lock held {new_worst[-1] * 1e3:.0f} ms "
            f"at most (one robot) with the percentiles under it, "
            f"{deferred_worst[-1] * 1e3:.1f} ms deferred",
            flush=True,
        )
    old, new, worst = (statistics.median(v) * 1e3 for v in (old_totals, new_totals, new_worst))
    print(
        f"\n{args.robots} robots x {args.topics} topics, full reservoirs, median of "
        f"{args.rounds}: the ingest lock was held {old:.0f} ms per summary, now {worst:.0f} ms "
        f"at a time ({old / worst:.0f}x shorter); the summary's work {new:.0f} ms "
        f"({old / new:.1f}x less); with the percentiles deferred, "
        f"{statistics.median(deferred_worst) * 1e3:.1f} ms at a time"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
