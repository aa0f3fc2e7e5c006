"""``python -m arpz.configure solve|instance|fit|figure5|characterise|apply``.

Exit codes: 0 done; 2 bad input (model file, CSV, arguments), with a message naming the file and
the problem; 3 no solution found (infeasible, or the time limit hit first); 1 a solver returned an
infeasible allocation (a bug: the independent checker caught it).
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

from arpz.configure import METHODS, solve
from arpz.configure.check import check
from arpz.configure.model import ModelError, dump_json, dump_toml, load_model
from arpz.configure.regression import FitError, candidate_fits, fit
from arpz.configure.report import as_dict, as_text
from arpz.runtime.startup import (
    JSON_TO_STDOUT,
    add_json_option,
    add_version_option,
    emit_json,
    fail,
)


def _fail(message: str) -> int:
    return fail("configure", message)


def cmd_solve(args: argparse.Namespace) -> int:
    try:
        model = load_model(args.model)
    except ModelError as exc:
        return _fail(str(exc))
    solution = solve(model, problem=args.problem, method=args.method, time_limit_s=args.time_limit)
    if args.json != JSON_TO_STDOUT:
        print(as_text(model, solution), end="")
    emit_json(as_dict(model, solution), args.json)
    if check(model, solution):
        return 1
    return 0 if solution.objective is not None else 3


def cmd_instance(args: argparse.Namespace) -> int:
    from arpz.configure.casestudy import case_study

    try:
        model = case_study(args.robots, args.cameras, args.computers, step=args.step)
    except ValueError as exc:
        return _fail(str(exc))
    text = dump_toml(model).encode() if args.format == "toml" else dump_json(model)
    if args.out:
        Path(args.out).write_bytes(text)
        print(
            f"wrote {args.out}: {len(model.nodes)} nodes, {len(model.computers)} computers, "
            f"{len(model.links)} links, {len(model.messages)} messages"
        )
    else:
        sys.stdout.write(text.decode())
    return 0


def _read_points(path: str) -> tuple[list[float], list[float]]:
    """CSV of (cpu, performance) rows; a header row and extra columns are ignored."""
    cpu: list[float] = []
    perf: list[float] = []
    with open(path, newline="") as handle:
        for i, row in enumerate(csv.reader(handle)):
            if not row or row[0].strip().startswith("#"):
                continue
            try:
                u, p = float(row[0]), float(row[1])
            except (ValueError, IndexError):
                if i == 0:
                    continue  # header
                raise ValueError(f"row {i + 1}: expected two numbers (cpu, performance)") from None
            cpu.append(u)
            perf.append(p)
    return cpu, perf


def cmd_fit(args: argparse.Namespace) -> int:
    try:
        cpu, perf = _read_points(args.points)
        chosen = fit(cpu, perf, args.kind)
    except OSError as exc:
        return _fail(f"{args.points}: {exc.strerror or exc}")
    except (ValueError, FitError) as exc:
        return _fail(f"{args.points}: {exc}")
    curves = candidate_fits(cpu, perf)
    emit_json(
        {
            "chosen": {
                "kind": chosen.kind,
                "coefficients": chosen.coefficients,
                "r2": chosen.r2,
                "equation": chosen.equation(),
            },
            "candidates": [
                {"kind": c.kind, "coefficients": c.coefficients, "r2": c.r2} for c in curves
            ],
        },
        args.json,
    )
    if args.json == JSON_TO_STDOUT:
        return 0
    print(f"{len(cpu)} points from {args.points} (x = cpu / 100)")
    for curve in curves:
        mark = "*" if curve.kind == chosen.kind else " "
        print(f"{mark} {curve.kind:<7} R^2 = {curve.r2:.5f}   {curve.equation()}")
    print(f"chosen: {chosen.kind}")
    return 0


def cmd_figure5(args: argparse.Namespace) -> int:
    from arpz.configure import figure5

    fleets = [tuple(int(x) for x in spec.split(",")) for spec in args.fleet]
    models = figure5.instances(range(1, args.instances + 1), fleets)  # type: ignore[arg-type]
    print(figure5.HEADER, flush=True)
    rows = figure5.run(
        models, time_limit_s=args.time_limit, progress=lambda line: print(line, flush=True)
    )
    if args.png:
        figure5.draw(rows, args.png)
        print(f"wrote {args.png}")
    return 0


def cmd_characterise(args: argparse.Namespace) -> int:
    from arpz.configure.characterise import main as run_characterise

    return run_characterise(args)


def parser() -> argparse.ArgumentParser:
    top = argparse.ArgumentParser(
        prog="python -m arpz.configure",
        description="Automatic configuration of node settings and placement (Cano et al. 2016).",
    )
    add_version_option(top)
    sub = top.add_subparsers(dest="command", required=True)

    p = sub.add_parser("solve", help="solve Problem 1 or 2 of a model file")
    p.add_argument("model", help="model file (.json or .toml)")
    p.add_argument(
        "--problem",
        type=int,
        choices=(1, 2),
        default=1,
        help="1: maximise weighted performance; 2: minimise server capacity",
    )
    p.add_argument("--method", choices=METHODS, default="improved")
    p.add_argument(
        "--time-limit", type=float, default=60.0, help="seconds (exact; improved uses at most 10)"
    )
    add_json_option(p, "one JSON object")
    p.set_defaults(func=cmd_solve)

    p = sub.add_parser("instance", help="write the paper's case study as a model file")
    p.add_argument("--robots", type=int, required=True)
    p.add_argument("--cameras", type=int, required=True)
    p.add_argument("--computers", type=int, required=True, help="robots + servers")
    p.add_argument("--step", type=int, default=1, help="CPU step of the continuum")
    p.add_argument("--format", choices=("json", "toml"), default="json")
    p.add_argument("--out", help="file to write (default: stdout)")
    p.set_defaults(func=cmd_instance)

    p = sub.add_parser("fit", help="fit linear, log and quadratic curves to cpu,performance")
    p.add_argument("points", help="CSV file: cpu,performance per row (header optional)")
    p.add_argument("--kind", choices=("best", "linear", "log", "poly2"), default="best")
    add_json_option(p, "the fits")
    p.set_defaults(func=cmd_fit)

    p = sub.add_parser("figure5", help="greedy vs exact vs improved on the paper's instances")
    p.add_argument("--instances", type=int, default=10, help="paper instances 1..N (max 10)")
    p.add_argument(
        "--fleet",
        action="append",
        default=[],
        metavar="R,K,C",
        help="add a fleet of R robots, K cameras, C computers (repeatable)",
    )
    p.add_argument("--time-limit", type=float, default=60.0)
    p.add_argument("--png", help="write the figure here")
    p.set_defaults(func=cmd_figure5)

    p = sub.add_parser("characterise", help="build a model file from a running fleet")
    p.add_argument("--connect", required=True, help="Zenoh endpoint, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--fleet", default="demo")
    p.add_argument("--duration", type=float, default=10.0, help="seconds to listen")
    p.add_argument("--out", required=True, help="model file to write (.json or .toml)")
    p.add_argument("--server-capacity", type=float, default=400.0)
    p.add_argument("--robot-capacity", type=float, default=100.0)
    p.add_argument(
        "--link-bandwidth",
        type=float,
        default=54000.0,
        help="bytes/s shared by the wireless links (default 54000)",
    )
    p.add_argument("--expected", help="a previous model file: report eq. 10 against it")
    p.set_defaults(func=cmd_characterise)

    from arpz.configure.apply import add_parser as add_apply_parser

    add_apply_parser(sub)
    return top


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    code: int = args.func(args)
    return code


if __name__ == "__main__":
    sys.exit(main())
