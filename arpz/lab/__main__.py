"""``python -m arpz lab``: the kernel network lab (namespaces, an access point, nftables loss,
dead zones, roaming, tbf), with the real CEDDP and robots inside it.

    python -m arpz lab run --robots 2 --profile robot1=dead-zone-12s --link tcp --duration 60
    python -m arpz lab profiles
    python -m arpz lab clean            # what a killed run left (labs of live owners stay)

Needs root (CAP_NET_ADMIN and CAP_SYS_ADMIN), ``nft`` and ``ip``. docs/netem.md, "The kernel
lab", has the topology and the profiles' numbers.
"""

from __future__ import annotations

import argparse
import signal
import sys
import tempfile
from dataclasses import asdict
from pathlib import Path

from arpz.core.errors import ArpzError
from arpz.lab.clean import clean
from arpz.lab.fleet import LINKS, LabRunOptions, run_lab
from arpz.lab.names import LabInterrupted, LabUnavailable
from arpz.lab.profiles import PARAMETRISED, PROFILES
from arpz.runtime.startup import (
    JSON_TO_STDOUT,
    add_json_option,
    add_version_option,
    emit_json,
    fail,
)
from arpz.tools.demo import DemoOptions, format_summary


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m arpz lab",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_version_option(parser)
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    run = commands.add_parser("run", help="a CEDDP and robots inside a lab, profiles applied")
    run.add_argument("--robots", type=int, default=2)
    run.add_argument(
        "--profile",
        action="append",
        default=[],
        metavar="[ROBOT=]PROFILE",
        help="a robot's link profile (repeatable); without ROBOT= for every robot not named "
        "(default clean); `python -m arpz lab profiles` lists them",
    )
    run.add_argument("--link", choices=LINKS, default="tcp", help="the robots' Zenoh link")
    run.add_argument("--duration", type=float, default=60.0, help="seconds of profiles")
    run.add_argument("--seed", type=int, default=0, help="the bursts' random draws")
    run.add_argument(
        "--workdir", type=Path, help="configs, logs, summary, timeline (default: temp)"
    )
    run.add_argument("--rate", type=float, help="sensor rate in Hz (as in `arpz demo`)")
    run.add_argument("--rmax", type=float, help="QoS balancing optimiser Rmax (Hz)")
    run.add_argument("--no-qos", action="store_true", help="no QoS optimiser")
    run.add_argument(
        "--reliability", choices=["reliable", "best_effort", "none"], default="reliable"
    )
    run.add_argument("--history", choices=["keep_last", "keep_all"], default="keep_last")
    run.add_argument("--depth", type=int, default=10)
    add_json_option(run, "the summary, the timeline's path and the links' counters")
    clean_cmd = commands.add_parser("clean", help="remove what killed labs left")
    clean_cmd.add_argument(
        "--all", action="store_true", help="also the labs of processes still running"
    )
    commands.add_parser("profiles", help="the named profiles and their numbers")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        if args.command == "clean":
            for line in clean(include_live=args.all).lines():
                print(f"arpz lab clean: {line}")
            return 0
        if args.command == "profiles":
            for name, profile in PROFILES.items():
                print(f"{name:16} {profile.description}")
            print(f"\nparametrised: {PARAMETRISED}")
            return 0
        return _run(args)
    except LabUnavailable as exc:
        return fail("lab", str(exc), 2)
    except ValueError as exc:
        return fail("lab", str(exc), 2)
    except ArpzError as exc:
        return fail("lab", f"FAILED: {exc}", 1)


def _run(args: argparse.Namespace) -> int:
    # as `arpz demo`: giving --rate forces it (no QoS optimiser unless --rmax is given too)
    forced = args.rate is not None and args.rmax is None
    rmax = 0.0 if (args.no_qos or forced) else (args.rmax or 500.0)
    options = LabRunOptions(
        robots=args.robots,
        link=args.link,
        duration_s=args.duration,
        profiles=tuple(args.profile),
        seed=args.seed,
        demo=DemoOptions(
            rate_hz=args.rate if args.rate is not None else 50.0,
            rmax_hz=rmax,
            reliability=args.reliability,
            history=args.history,
            depth=args.depth,
        ),
    )
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="arpz-lab-"))
    # the first SIGINT/SIGTERM ends the run early but cleanly (summary, teardown); a second one
    # interrupts whatever is under way, and the lab is still torn down on the way out
    stopping: list[int] = []

    def on_signal(signum: int, _frame: object) -> None:
        if stopping:
            raise LabInterrupted(f"stopped by a second {signal.Signals(signum).name}")
        stopping.append(signum)
        print(f"\nlab: {signal.Signals(signum).name}: stopping the run", file=sys.stderr)

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        result = run_lab(options, workdir, stop_requested=lambda: bool(stopping))
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    words = sys.stderr if args.json == JSON_TO_STDOUT else sys.stdout
    print(format_summary(result.summary), file=words)
    for problem in result.problems:
        print(f"lab: note: {problem}", file=words)
    for robot, counters in result.counters.items():
        print(
            f"lab: {robot}'s link: up {counters.up_dropped}/{counters.up_seen} frames dropped, "
            f"down {counters.down_dropped}/{counters.down_seen}",
            file=words,
        )
    print(f"lab: timeline {result.timeline}, summary {workdir / 'summary.json'}", file=words)
    emit_json(
        {
            "summary": result.summary,
            "timeline": str(result.timeline),
            "problems": result.problems,
            "counters": {r: asdict(c) for r, c in result.counters.items()},
        },
        args.json,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
