"""Solve time of the QoS balancing optimiser: closed form vs CVXPY (seed 001, problem 6).

Why it matters: the CEDDP re-solves whenever the fleet changes, so the solve sits on the path
from "a robot joined" to "every robot runs at the new R and D". The paper solves with CVXPY;
the closed form gives the same optimum (tested) and this measures what that saves.

Run:  python benchmarks/optimiser_solve_time.py [--closed-reps N] [--cvxpy-reps N]

Each setting is timed as the median of repeated solves in the same process (the first CVXPY
solve, which pays for imports and solver start-up, is a separate warm-up). Progress goes to
stderr, the Markdown table to stdout.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time
from collections.abc import Callable
from functools import partial
from typing import Any

from arpz.ceddp.optimiser import QosLimits, QosSolution, solve_closed, solve_cvxpy

#: progress lines, printed as they come
SAY = partial(print, file=sys.stderr, flush=True)

SETTINGS: list[tuple[str, list[int]]] = [
    ("6,5,5 (sensor topics)", [6, 5, 5]),
    ("7,6,6 (+ received topic, eq. 1)", [7, 6, 6]),
]
RMAX_HZ = (100.0, 200.0, 500.0, 1000.0)


def _median_s(
    solver: Callable[..., QosSolution],
    limits: QosLimits,
    topics: list[int],
    reps: int,
    **options: Any,
) -> float:
    samples = []
    for _ in range(reps):
        start = time.perf_counter()
        solver(limits, topics, **options)
        samples.append(time.perf_counter() - start)
    return statistics.median(samples)


#: (setting, Rmax, R, D, closed-form s, CVXPY lexicographic s, CVXPY weighted s)
Row = tuple[str, float, float, int, float, float, float]


def measure(
    closed_reps: int,
    cvxpy_reps: int,
    settings: list[tuple[str, list[int]]] = SETTINGS,
    rmax_hz: tuple[float, ...] = RMAX_HZ,
    log: Callable[[str], object] = SAY,
) -> list[Row]:
    """The median solve of each method in each setting, after a first CVXPY solve (imports,
    solver start-up) that is not counted."""
    start = time.perf_counter()
    solve_cvxpy(QosLimits(rmax_hz=100, rmin_hz=1), [6, 5, 5])
    log(f"warm-up (first CVXPY solve, imports included): {time.perf_counter() - start:.2f} s")
    rows: list[Row] = []
    total = len(settings) * len(rmax_hz)
    for name, topics in settings:
        for rmax in rmax_hz:
            limits = QosLimits(rmax_hz=rmax, rmin_hz=1.0, dmax=5000, dmin=1)
            closed = solve_closed(limits, topics)
            cvx = solve_cvxpy(limits, topics)
            assert cvx.depth == closed.depth, (name, rmax)
            closed_s = _median_s(solve_closed, limits, topics, closed_reps)
            cvxpy_s = _median_s(solve_cvxpy, limits, topics, cvxpy_reps)
            # One weighted MILP, closer to a single CVXPY call as the paper may have made it.
            one_s = _median_s(solve_cvxpy, limits, topics, cvxpy_reps, weights=(1.0, 1.0))
            rows.append((name, rmax, closed.rate_hz, closed.depth, closed_s, cvxpy_s, one_s))
            log(
                f"[{len(rows)}/{total}] T={name} Rmax={rmax:g} Hz: "
                f"closed {closed_s * 1e6:.1f} us, cvxpy {cvxpy_s * 1e3:.2f} ms "
                f"(one stage {one_s * 1e3:.2f} ms), ratio {cvxpy_s / closed_s:.0f}x"
            )
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--closed-reps", type=int, default=2000)
    parser.add_argument("--cvxpy-reps", type=int, default=30)
    args = parser.parse_args()
    rows = measure(args.closed_reps, args.cvxpy_reps)
    print(
        f"Python {platform.python_version()}, {platform.machine()}, "
        f"closed reps {args.closed_reps}, cvxpy reps {args.cvxpy_reps} (medians)\n"
    )
    print(
        "| T_a | Rmax (Hz) | R (Hz) | D | closed form | CVXPY lexicographic (2 MILPs) "
        "| CVXPY weighted (1 MILP) | CVXPY / closed |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for name, rmax_hz, rate_hz, depth, closed_s, cvxpy_s, one_s in rows:
        print(
            f"| {name} | {rmax_hz:g} | {rate_hz:.4g} | {depth} | {closed_s * 1e6:.1f} us "
            f"| {cvxpy_s * 1e3:.2f} ms | {one_s * 1e3:.2f} ms | {cvxpy_s / closed_s:.0f}x |"
        )
    ratios = [row[5] / row[4] for row in rows]
    print(
        f"\nmedian ratio CVXPY / closed form: {statistics.median(ratios):.0f}x "
        f"(range {min(ratios):.0f}x - {max(ratios):.0f}x)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
