"""Fault grids over the offline closed loop: the hallway mission run once per outage start or per
seed, counted as successes (S), timeouts (T, failed safe) and collisions (C).

docs/simulation.md's tables of robots cut off come from these grids::

    python -m arpz.mission.grid sweep --kind downlink --robots robot1 robot2 robot3
    python -m arpz.mission.grid intermittent --kind downlink --robots robot2
    python -m arpz.mission.grid sweep --kind downlink --set max_command_age_s=inf   # not watched

- ``sweep``: one outage of each robot named (in turn) of 3 s and of 12 s, starting at each
  0.5 s from 1 to 59.5 s (118 runs per robot and duration);
- ``intermittent``: over the whole run, each robot named (together) down 0.05-0.8 s every
  0.3-4 s (uniform draws), 30 seeds.

Every run: 20 Hz beams, noise 0.01 m, time limit 150 s, the run's seed for noise and phases.
"""

from __future__ import annotations

import argparse
import random
import sys
from collections import Counter
from collections.abc import Iterator, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from typing import Literal

import msgspec

from arpz.mission.hallway import PlannerSettings
from arpz.mission.offline import Outage, run_offline
from arpz.mission.world import World

Kind = Literal["link", "uplink", "downlink", "frozen"]
Verdict = Literal["S", "T", "C"]
#: the sweep's outage lengths: shorter and longer than Zenoh's 10 s lease
SWEEP_DURATIONS_S = (3.0, 12.0)
TIME_LIMIT_S = 150.0


@dataclass(frozen=True)
class Case:
    """One offline run of a grid: its row label, world, outages and seed."""

    label: str
    world: str
    outages: tuple[Outage, ...]
    seed: int = 0


def sweep(
    world: str, kind: Kind, robots: Sequence[str], durations_s: Sequence[float] = SWEEP_DURATIONS_S
) -> Iterator[Case]:
    """One outage of one robot per run, starting at each 0.5 s from 1 to 59.5 s."""
    for robot in robots:
        for duration_s in durations_s:
            for index in range(118):
                outage = Outage(robot, 1.0 + 0.5 * index, duration_s, kind)
                yield Case(f"{robot} {kind} {duration_s:g} s", world, (outage,))


def intermittent(world: str, kind: Kind, robots: Sequence[str], seeds: int = 30) -> Iterator[Case]:
    """Every robot named down 0.05-0.8 s every 0.3-4 s for the whole run, one seed a run."""
    for seed in range(seeds):
        draw = random.Random(seed)
        outages = []
        for robot in robots:
            t_s = 1.0
            while (t_s := t_s + draw.uniform(0.3, 4.0)) < TIME_LIMIT_S:
                duration_s = draw.uniform(0.05, 0.8)
                outages.append(Outage(robot, t_s, duration_s, kind))
                t_s += duration_s
        yield Case(f"{'+'.join(robots)} {kind} intermittent", world, tuple(outages), seed)


def verdict(case: Case, overrides: Mapping[str, float] | None = None) -> Verdict:
    """Run one case with the map's planner settings (and ``overrides`` of their fields)."""
    world = World.load(case.world)
    settings = PlannerSettings.for_world(world, **(overrides or {}))
    result = run_offline(
        world,
        settings,
        20.0,
        TIME_LIMIT_S,
        noise_std_m=0.01,
        seed=case.seed,
        outages=case.outages,
    ).result
    if result.mission == "success":
        return "S"
    return "C" if result.failure == "collision" else "T"


def tally(
    cases: Sequence[Case], overrides: Mapping[str, float] | None = None, jobs: int = 1
) -> dict[tuple[str, str], Counter[Verdict]]:
    """Per (world, label), how many runs ended in each verdict."""
    each = [overrides] * len(cases)
    if jobs > 1:
        with ProcessPoolExecutor(jobs) as pool:
            verdicts = list(pool.map(verdict, cases, each, chunksize=4))
    else:
        verdicts = [verdict(case, o) for case, o in zip(cases, each, strict=True)]
    counts: dict[tuple[str, str], Counter[Verdict]] = {}
    for case, result in zip(cases, verdicts, strict=True):
        counts.setdefault((case.world, case.label), Counter())[result] += 1
    return counts


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m arpz.mission.grid", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("grid", choices=("sweep", "intermittent"))
    parser.add_argument("--kind", choices=("link", "uplink", "downlink", "frozen"), default="link")
    parser.add_argument("--robots", nargs="+", default=["robot1"])
    parser.add_argument("--worlds", nargs="+", default=["hallway"])
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="a PlannerSettings number, e.g. max_command_age_s=inf (not watched) or "
        "catch_up_rad_s=0 (no catch-up); repeat for more",
    )
    parser.add_argument("--jobs", type=int, default=1, help="processes to run the grid on")
    args = parser.parse_args(argv)
    cases: list[Case] = []
    for world in args.worlds:
        if args.grid == "sweep":
            cases += sweep(world, args.kind, args.robots)
        else:
            cases += intermittent(world, args.kind, args.robots)
    overrides: dict[str, float] = {}
    for item in args.set:
        field, sep, value = item.partition("=")
        try:
            if not sep or field not in PlannerSettings.__struct_fields__:
                raise ValueError("not FIELD=VALUE with a PlannerSettings field")
            overrides[field] = float(value)
        except ValueError as exc:
            parser.error(f"--set {item!r}: {exc}")
    try:
        msgspec.convert(overrides, type=PlannerSettings)  # checked once, here
    except (msgspec.ValidationError, ValueError) as exc:
        parser.error(f"--set: {exc}")
    shown = ", ".join(f"{k}={v:g}" for k, v in overrides.items()) or "default settings"
    print(f"{len(cases)} runs, {shown}")
    for (world, label), counts in tally(cases, overrides, args.jobs).items():
        row = ", ".join(f"{counts[v]} {v}" for v in ("S", "T", "C") if counts[v])
        print(f"{world:14} {label:32} {row}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
