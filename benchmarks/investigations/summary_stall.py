"""What the CEDDP's periodic summary costs, with whole-run histograms against the reservoirs
they replaced, in one run.

The CEDDP persists its summary every ``summary_period_s`` (5 s). Each robot's row holds p50 and
p99 of every topic's latency and staleness over the whole run, and of its topics pooled. Until
stop 35 of issue 17 they came from uniform reservoirs of up to 20 000 values a topic (sorted for
every summary, concatenated and sorted again a robot); now from ``LogHistogram`` counts (a
cumulative sum, whatever the count; pooled by adding counts). This fills N robots x T topics as
a run of ``--seconds`` at ``--rate-hz`` would, then times, per round:

- the summary as the server builds it: each robot's row under the ingest lock with the
  percentiles deferred (``robot_summary(defer=True)``, the lock's hold), then ``resolve``;
- the baseline: the same figures from reservoirs (what ``resolve`` cost before: one sort a topic
  and figure set, one sort of the pooled topics a robot).

    python benchmarks/investigations/summary_stall.py [--robots 50] [--topics 8] [--seconds 200]
        [--rounds 3]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections import deque
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from arpz.ceddp.cache_control import CacheControl
from arpz.ceddp.control import RobotRecord
from arpz.ceddp.ingest import Ingest
from arpz.ceddp.planner import Planner
from arpz.ceddp.summary import resolve, robot_summary
from arpz.core.messages import Sample, encode
from arpz.core.percentiles import percentiles

#: the reservoir arpz kept a topic's whole-run values in before the histograms
RESERVOIR = 20_000


def filled(robots: int, topics: int, values: int) -> tuple[Ingest, dict[str, list[np.ndarray]]]:
    """An ingest whose topics saw ``values`` latencies and staleness values each (folded as
    the metrics tick folds them), and the reservoirs the same values would have filled."""
    ingest = Ingest("f", Planner(), CacheControl(enabled=True))
    rng = np.random.default_rng(1)
    reservoirs: dict[str, list[np.ndarray]] = {}
    for r in range(robots):
        for t in range(topics):
            key = f"arpz/f/robot/r{r}/sensor/t{t}"
            ingest.handle_sensor(key, encode(Sample(f"r{r}:a", 1, 1, 1.0)), 2)
            m = ingest.topics[(f"r{r}", f"t{t}")]
            for dist in (m.latency_ms, m.staleness_ms):
                series = rng.lognormal(0.0, 1.0, values)
                for window in np.array_split(series, max(1, values // 50)):
                    deque(map(dist.add, window.tolist()), maxlen=0)
                    dist.take_window()
                reservoirs.setdefault(f"r{r}", []).append(series[:RESERVOIR].copy())
    return ingest, reservoirs


def reservoir_figures(arrays: list[np.ndarray]) -> None:
    """The old ``resolve``: p50/p99 of each topic's two reservoirs, and of the robot's pooled
    latency and staleness reservoirs."""
    for values in arrays:
        percentiles(values, (50, 99))
    percentiles(np.concatenate(arrays[0::2]), (50, 99))
    percentiles(np.concatenate(arrays[1::2]), (99,))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=50)
    ap.add_argument("--topics", type=int, default=8)
    ap.add_argument("--seconds", type=float, default=200.0, help="the run's length so far")
    ap.add_argument("--rate-hz", type=float, default=100.0)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    values = int(args.seconds * args.rate_hz)
    print(
        f"filling {args.robots} x {args.topics} topics with {values} values each "
        f"({args.seconds:.0f} s at {args.rate_hz:.0f} Hz) ...",
        flush=True,
    )
    ingest, reservoirs = filled(args.robots, args.topics, values)
    names = [f"r{r}" for r in range(args.robots)]
    summaries, holds, baselines = [], [], []
    for round_ in range(1, args.rounds + 1):
        started = time.perf_counter()
        held = []
        for robot in names:
            t0 = time.perf_counter()
            row = robot_summary(ingest, robot, RobotRecord().as_report(), defer=True)
            held.append(time.perf_counter() - t0)
            resolve(row)
        summaries.append(time.perf_counter() - started)
        holds.append(max(held))
        started = time.perf_counter()
        for robot in names:
            reservoir_figures(reservoirs[robot])
        baselines.append(time.perf_counter() - started)
        print(
            f"round {round_}/{args.rounds}: summary {summaries[-1] * 1e3:.1f} ms (lock held "
            f"{holds[-1] * 1e3:.2f} ms at most); the reservoirs' percentiles alone "
            f"{baselines[-1] * 1e3:.1f} ms",
            flush=True,
        )
    summary, hold, baseline = (statistics.median(v) * 1e3 for v in (summaries, holds, baselines))
    print(
        f"\n{args.robots} robots x {args.topics} topics, {values} values a topic, median of "
        f"{args.rounds}: the summary {summary:.1f} ms with histograms (the ingest lock held "
        f"{hold:.2f} ms at a time); the percentiles from {RESERVOIR}-value reservoirs alone "
        f"{baseline:.1f} ms; ratio {summary / baseline:.2f}x"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
