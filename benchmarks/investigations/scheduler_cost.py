"""What a robot's scheduler costs a tick, apart from the jobs it runs: ``Scheduler.run_due`` of
a robot like the fleet's (8 sensor jobs at 100 Hz inside the tick's context, 4 slower jobs:
reports, probes, clock) against the floor, the same 8 no-op jobs called in the same context
with no scheduler, in one run. The load generator of ``python -m arpz.perf fleet`` runs 12-13
robots' schedulers on one thread of each worker. Until ec1d213 it called every robot whenever
any one was due, so each tick also peeked at the other robots' heaps: ``--peeks 11`` counts
those not-due calls with every tick (stop 40's figures, README.md here, were taken so).
Since then a worker calls a robot only when its next job is due: the default, ``--peeks 0``.

    python benchmarks/investigations/scheduler_cost.py [--ticks 50000] [--rounds 3] [--peeks 0]
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from arpz.robot.scheduler import Scheduler

PERIOD_S = 0.01
SENSORS = 8
#: the slower jobs' periods (s): stats, Hello probe, announce, clock exchange
OTHER_PERIODS_S = (1.0, 0.05, 5.0, 1.0)


def _noop(_now_s: float) -> None:
    return None


def scheduled_us(ticks: int, peeks: int) -> float:
    """Wall us a tick of ``Scheduler.run_due`` with ``peeks`` not-due calls beside it."""
    scheduler = Scheduler()
    for i in range(SENSORS):
        scheduler.every(PERIOD_S, _noop, f"t{i:02d}", in_tick=True)
    for period in OTHER_PERIODS_S:
        scheduler.every(period, _noop, "other")
    tick = contextlib.nullcontext
    now = 0.0
    start = time.perf_counter()
    for _ in range(ticks):
        now += PERIOD_S
        scheduler.run_due(now, tick=tick)
        for _ in range(peeks):
            scheduler.run_due(now)
    return (time.perf_counter() - start) / ticks * 1e6


def floor_us(ticks: int) -> float:
    """Wall us a tick of calling the 8 sensor jobs in the tick's context, no scheduler."""
    jobs = [_noop] * SENSORS
    tick = contextlib.nullcontext
    now = 0.0
    start = time.perf_counter()
    for _ in range(ticks):
        now += PERIOD_S
        with tick():
            for job in jobs:
                job(now)
    return (time.perf_counter() - start) / ticks * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ticks", type=int, default=50_000)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument(
        "--peeks",
        type=int,
        default=0,
        help="not-due calls a tick (0; 11: a fleet worker before ec1d213)",
    )
    args = ap.parse_args()
    if args.ticks < 1 or args.rounds < 1 or args.peeks < 0:
        ap.error(
            "need --ticks, --rounds >= 1, --peeks >= 0; "
            f"got {args.ticks}, {args.rounds}, {args.peeks}"
        )
    scheduled: list[float] = []
    floor: list[float] = []
    for round_ in range(args.rounds):
        scheduled.append(scheduled_us(args.ticks, args.peeks))
        floor.append(floor_us(args.ticks))
        print(
            f"round {round_ + 1}/{args.rounds}: scheduler {scheduled[-1]:.2f} us a tick, "
            f"floor {floor[-1]:.2f} us",
            flush=True,
        )
    s, f = statistics.median(scheduled), statistics.median(floor)
    print()
    print("| a robot tick (8 sensor jobs, 4 others) | us | / floor |")
    print("|---|---|---|")
    print(f"| `Scheduler.run_due` (+ {args.peeks} not-due calls) | {s:.2f} | {s / f:.1f}x |")
    print(f"| floor: the 8 jobs called in the tick's context | {f:.2f} | 1.0x |")


if __name__ == "__main__":
    main()
