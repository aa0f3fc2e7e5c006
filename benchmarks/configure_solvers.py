"""Greedy vs exact vs improved on the paper's instances and on fleets of 10, 20 and 50 robots.

Prints one Markdown table row per (instance, problem) as it goes, each method's objective
relative to the exact MILP (the reference measured in the same run) and the solve times, then
writes docs/figures/configure_figure5.png. Every solution is checked by the independent checker.

    python benchmarks/configure_solvers.py [--time-limit 120] [--quick]
"""

from __future__ import annotations

import argparse
import platform
import time

from arpz.configure import figure5


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--time-limit", type=float, default=120.0)
    ap.add_argument("--quick", action="store_true", help="paper instances only")
    ap.add_argument("--png", default="docs/figures/configure_figure5.png")
    args = ap.parse_args()
    fleets = [] if args.quick else [(10, 4, 11), (20, 4, 22), (50, 4, 55)]
    models = figure5.instances(range(1, 11), fleets)
    print(f"# configure solvers, {platform.python_version()}, time limit {args.time_limit} s")
    print("# fleets: (robots, cameras, computers) =", fleets)
    print(figure5.HEADER, flush=True)
    start = time.perf_counter()
    rows = figure5.run(
        models, time_limit_s=args.time_limit, progress=lambda line: print(line, flush=True)
    )
    figure5.draw(rows, args.png)
    for kind in (1, 2):
        sel = [r for r in rows if r.problem == kind]
        for method in ("greedy", "improved"):
            ratios = [r.ratio(method) for r in sel]
            values = [v for v in ratios if v is not None]
            if values:
                worst = min(values) if kind == 1 else max(values)
                mean = sum(values) / len(values)
                print(f"P{kind} {method}/exact: mean {mean:.4f}, worst {worst:.4f}")
    print(f"wrote {args.png}; total {time.perf_counter() - start:.1f} s")


if __name__ == "__main__":
    main()
