"""``optimise``: the QoS balancing optimiser of seed 001 from the command line.

Called as ``python -m arpz.ceddp optimise ...`` (the CEDDP entry point hands over the arguments
after ``optimise``) or directly as ``python -m arpz.ceddp.optimise_cli ...``. It exists so an
operator can size R and D for a fleet before starting it, and see which bound is in the way
when the numbers do not fit. Usage errors and infeasible inputs exit with code 2 and a message
on stderr; ``--json`` prints exactly one JSON object on stdout so scripts can consume it.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, cast

import msgspec

from arpz.ceddp.optimiser import (
    DEFAULT_DMAX,
    DEFAULT_DMIN,
    DEFAULT_RESIDUAL_LOSS,
    DEPTH_POLICIES,
    FASTDDS_HEARTBEAT_PERIOD_S,
    FASTDDS_NACK_DELAY_S,
    LinkQuality,
    Method,
    OptimiserError,
    QosAssignment,
    QosLimits,
    assign_qos,
    solve_closed,
)
from arpz.ceddp.topic_optimiser import TopicMethod, TopicSolution, solve_topics
from arpz.ceddp.topic_problem import TopicProblem, load_problem, solution_document
from arpz.core.errors import ArpzError
from arpz.core.traffic import SENSOR_QOS
from arpz.runtime.startup import JSON_TO_STDOUT, add_json_option, add_version_option, fail

EXIT_USAGE = 2
EXIT_DISAGREE = 1


class _UsageError(ArpzError):
    pass


class _Parser(argparse.ArgumentParser):
    """Raises instead of exiting, so ``main()`` returns its code and tests can call it."""

    def error(self, message: str) -> Any:
        raise _UsageError(f"{self.prog}: error: {message}")


def _topics(text: str) -> list[int]:
    try:
        counts = [int(part) for part in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated topic counts per agent such as 6,5,5, got {text!r}"
        ) from None
    return counts


def _parser() -> _Parser:
    parser = _Parser(
        prog="optimise",
        description=(
            "Balance the DEADLINE rate R and the KEEP_LAST depth D of every topic "
            "(seed 001, problem 6)."
        ),
    )
    parser.add_argument(
        "--problem",
        type=Path,
        metavar="FILE.toml",
        help="solve the per-topic problem of this file (rmax_hz, rmin_hz, dmax, dmin, "
        "[[robots]] with [[robots.topics]]: name, weight, change_hz); see "
        "examples/qos_problem.toml",
    )
    parser.add_argument("--rmax", type=float, metavar="HZ", help="Rmax, Hz")
    parser.add_argument("--rmin", type=float, metavar="HZ", help="Rmin, Hz")
    parser.add_argument(
        "--dmax", type=int, default=DEFAULT_DMAX, metavar="N", help="Dmax, samples (5000)"
    )
    parser.add_argument(
        "--dmin", type=int, default=DEFAULT_DMIN, metavar="N", help="Dmin, samples (1)"
    )
    parser.add_argument(
        "--topics",
        type=_topics,
        metavar="T1,T2,...",
        help="topics per agent T_a (sensor topics + received localisation/command topics)",
    )
    link = parser.add_argument_group(
        "loss-aware depth (all optional; needs --rtt-ms and --loss-pct)"
    )
    link.add_argument("--rtt-ms", type=float, metavar="X", help="link round trip, ms")
    link.add_argument("--loss-pct", type=float, metavar="Y", help="link loss rate, %%")
    link.add_argument(
        "--heartbeat-ms",
        type=float,
        default=SENSOR_QOS.heartbeat_period_s * 1000,
        metavar="H",
        help="reliable channel heartbeat period, ms (arpz's sensor profile: "
        f"{SENSOR_QOS.heartbeat_period_s * 1000:g}; "
        f"Fast DDS: {FASTDDS_HEARTBEAT_PERIOD_S * 1000:g})",
    )
    link.add_argument(
        "--nack-delay-ms",
        type=float,
        default=SENSOR_QOS.nack_delay_s * 1000,
        metavar="N",
        help="NACK response delay, ms (arpz's sensor profile: "
        f"{SENSOR_QOS.nack_delay_s * 1000:g}; Fast DDS: {FASTDDS_NACK_DELAY_S * 1000:g})",
    )
    link.add_argument(
        "--residual-loss",
        type=float,
        default=DEFAULT_RESIDUAL_LOSS,
        metavar="P",
        help="target probability that a sample is still missing (1e-6)",
    )
    parser.add_argument(
        "--depth-policy",
        choices=DEPTH_POLICIES,
        default="paper",
        help="paper: D of (6); loss_aware: the loss-aware depth; max: the larger (default paper)",
    )
    parser.add_argument("--method", choices=("closed", "cvxpy", "both"), default="closed")
    add_json_option(parser, "one JSON object")
    add_version_option(parser)
    return parser


def _link(args: argparse.Namespace) -> LinkQuality | None:
    if args.rtt_ms is None and args.loss_pct is None:
        return None
    if args.rtt_ms is None or args.loss_pct is None:
        raise _UsageError("the loss-aware depth needs both --rtt-ms and --loss-pct")
    return LinkQuality(
        rtt_s=args.rtt_ms / 1000,
        loss_pct=args.loss_pct,
        heartbeat_period_s=args.heartbeat_ms / 1000,
        nack_delay_s=args.nack_delay_ms / 1000,
        residual_loss=args.residual_loss,
    )


def _as_json(result: QosAssignment, topics: list[int], times_s: dict[str, float]) -> str:
    loss = None if result.loss is None else msgspec.to_builtins(result.loss)
    document = {
        "R": result.rate_hz,
        "D": result.depth,
        "T_avg": result.t_avg,
        "deadline_s": result.deadline_s,
        "paper_D": result.paper_depth,
        "depth_policy": result.depth_policy,
        "topics": topics,
        "binding": list(result.binding),
        "constraints": msgspec.to_builtins(result.constraints),
        "loss_aware": loss,
        "loss_safe": result.loss_safe,
        "paper_loss_safe": result.paper_loss_safe,
        "method": result.method,
        "solve_time_s": result.solve_time_s,
        "solve_times_s": times_s,
    }
    return msgspec.json.encode(document).decode()


def _duration(seconds: float) -> str:
    if seconds >= 1:
        return f"{seconds:.3g} s"
    if seconds >= 1e-3:
        return f"{seconds * 1e3:.3g} ms"
    return f"{seconds * 1e6:.3g} us"


def _as_text(result: QosAssignment, topics: list[int], times_s: dict[str, float]) -> str:
    lines = [
        "QoS balancing optimiser (seed 001, problem 6)",
        f"  T_a       {', '.join(map(str, topics))}  ->  T_avg = {result.t_avg:.4g}",
        f"  R         {result.rate_hz:.6g} Hz  (deadline period {_duration(result.deadline_s)})",
        f"  D         {result.paper_depth} samples (KEEP_LAST depth of problem 6)",
        "  binding   " + ("; ".join(result.binding) or "none"),
        "  constraints (slack; * = binding):",
    ]
    for c in result.constraints:
        lines.append(f"    {'*' if c.binding else ' '} {c.name:<30} {c.slack:.6g}")
    if result.loss is not None:
        loss = result.loss
        lines.append(
            f"  loss-aware depth {loss.depth} samples: {loss.rounds} recovery rounds of "
            f"{loss.round_s:.4g} s at R (residual loss {loss.residual_loss:.2g}); "
            f"paper D covers it: {'yes' if result.paper_loss_safe else 'NO'}"
        )
    if result.depth_policy != "paper" or result.loss is not None:
        safe = (
            ""
            if result.loss_safe is None
            else f", loss-safe: {'yes' if result.loss_safe else 'NO'}"
        )
        lines.append(f"  depth to apply ({result.depth_policy}): {result.depth} samples{safe}")
    timing = "; ".join(f"{m} {_duration(t)}" for m, t in times_s.items())
    if "closed" in times_s and "cvxpy" in times_s and times_s["closed"] > 0:
        timing += f" (cvxpy/closed = {times_s['cvxpy'] / times_s['closed']:.0f}x)"
    lines.append(f"  solve time {timing}")
    return "\n".join(lines)


def _agree(a: QosAssignment, b: QosAssignment, rmax_hz: float) -> bool:
    return abs(a.rate_hz - b.rate_hz) <= 1e-6 * rmax_hz and a.paper_depth == b.paper_depth


def _topic_text(problem: TopicProblem, document: dict[str, Any], fleet: str) -> str:
    lines = [
        "Per-topic QoS optimiser (max sum w log r; docs/qos-optimiser.md)",
        f"  capacity  {document['capacity_hz']:.6g} samples/s (A Rmax - N Rmin), used "
        f"{document['used_hz']:.6g}",
        f"  seed 001  {fleet}",
        f"  {'robot':<12} {'topic':<14} {'weight':>8} {'R (Hz)':>10} {'D':>6}  bound",
    ]
    for t in document["topics"]:
        lines.append(
            f"  {t['robot']:<12} {t['topic']:<14} {t['weight']:>8.4g} {t['R']:>10.5g} "
            f"{t['D']:>6}  {t['bound']}"
        )
    timing = "; ".join(f"{m} {_duration(s)}" for m, s in document["solve_times_s"].items())
    lines.append(f"  solve time {timing}")
    return "\n".join(lines)


def _topics_agree(a: TopicSolution, b: TopicSolution, rmax_hz: float) -> bool:
    """CLARABEL stops about 1e-6 Rmax short of the exact optimum: compare to 1e-3."""
    return all(
        abs(x.rate_hz - y.rate_hz) <= 1e-3 * max(x.rate_hz, 1e-3 * rmax_hz)
        for x, y in zip(a.topics, b.topics, strict=True)
    )


def _main_problem(args: argparse.Namespace) -> int:
    """``--problem FILE.toml``: the per-topic problem."""
    try:
        problem = load_problem(args.problem)
        limits, demands = problem.limits(), problem.demands()
        methods: tuple[TopicMethod, ...] = (
            ("closed", "cvxpy") if args.method == "both" else (cast(TopicMethod, args.method),)
        )
        results = {m: solve_topics(limits, demands, method=m) for m in methods}
    except OptimiserError as exc:
        return fail("ceddp optimise", str(exc), EXIT_USAGE)
    result = results[methods[0]]
    if len(results) == 2 and not _topics_agree(results["closed"], results["cvxpy"], limits.rmax_hz):
        return fail("ceddp optimise", "closed form and CVXPY disagree", EXIT_DISAGREE)
    document = solution_document(result)
    document["solve_times_s"] = {m: r.solve_time_s for m, r in results.items()}
    try:  # what seed 001 gives every topic of the same fleet, for comparison
        seed = solve_closed(limits, problem.topic_counts())
        document["fleet"] = {"R": seed.rate_hz, "D": seed.depth}
        fleet = f"R = {seed.rate_hz:.6g} Hz, D = {seed.depth} for every topic"
    except OptimiserError as exc:
        document["fleet"] = None
        fleet = f"infeasible ({exc.__class__.__name__})"
    text = json.dumps(document)
    if args.json is None:
        print(_topic_text(problem, document, fleet))
    elif args.json == JSON_TO_STDOUT:
        print(text)
    else:
        Path(args.json).write_text(text + "\n", encoding="utf-8")
        print(_topic_text(problem, document, fleet))
    return 0


def main(argv: list[str] | None = None) -> int:
    """Run ``optimise``; returns the exit code (0 ok, 1 methods disagree, 2 bad input)."""
    try:
        args = _parser().parse_args(argv)
        if args.problem is not None:
            if args.topics is not None:
                raise _UsageError("give either --problem or --topics, not both")
            return _main_problem(args)
        missing = [
            flag
            for flag, value in (
                ("--rmax", args.rmax),
                ("--rmin", args.rmin),
                ("--topics", args.topics),
            )
            if value is None
        ]
        if missing:
            raise _UsageError(
                f"optimise: error: {', '.join(missing)} required (or give --problem FILE.toml)"
            )
        link = _link(args)
        limits = QosLimits(rmax_hz=args.rmax, rmin_hz=args.rmin, dmax=args.dmax, dmin=args.dmin)
        agents = {f"agent{i + 1}": count for i, count in enumerate(args.topics)}
        methods: tuple[Method, ...] = (
            ("closed", "cvxpy") if args.method == "both" else (cast(Method, args.method),)
        )
        results = {
            m: assign_qos(limits, agents, depth_policy=args.depth_policy, link=link, method=m)
            for m in methods
        }
    except _UsageError as exc:
        return fail("ceddp optimise", str(exc), EXIT_USAGE)
    except OptimiserError as exc:
        return fail("ceddp optimise", str(exc), EXIT_USAGE)
    except SystemExit as exc:  # --help
        return exc.code if isinstance(exc.code, int) else 0
    result = results[methods[0]]
    times_s: dict[str, float] = {m: r.solve_time_s for m, r in results.items()}
    if len(results) == 2 and not _agree(results["closed"], results["cvxpy"], args.rmax):
        other = results["cvxpy"]
        print(
            "arpz ceddp optimise: error: "
            f"closed form (R={result.rate_hz!r}, D={result.paper_depth}) and CVXPY "
            f"(R={other.rate_hz!r}, D={other.paper_depth}) disagree",
            file=sys.stderr,
        )
        return EXIT_DISAGREE
    if args.json is None:
        print(_as_text(result, args.topics, times_s))
    elif args.json == JSON_TO_STDOUT:
        print(_as_json(result, args.topics, times_s))
    else:
        Path(args.json).write_text(_as_json(result, args.topics, times_s) + "\n", encoding="utf-8")
        print(_as_text(result, args.topics, times_s))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
