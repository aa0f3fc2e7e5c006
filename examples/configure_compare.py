"""Solve a model file with the three methods and print what each decided.

python examples/configure_compare.py [MODEL]   (default: examples/configure_two_robots.toml)
"""

from __future__ import annotations

import sys
from pathlib import Path

from arpz.configure import METHODS, check, load_model, solve


def main() -> int:
    path = (
        Path(sys.argv[1])
        if len(sys.argv) > 1
        else Path(__file__).with_name("configure_two_robots.toml")
    )
    model = load_model(path)
    for problem in (1, 2):
        print(f"Problem {problem} of {path.name}")
        for method in METHODS:
            solution = solve(model, problem=problem, method=method, time_limit_s=30)
            assert not check(model, solution), check(model, solution)
            where = ", ".join(
                f"{name}@{p.computer}:{p.cpu:g}" for name, p in solution.assignment.items()
            )
            print(f"  {method:<8} {solution.status:<9} {solution.objective:10.3f}  {where}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
