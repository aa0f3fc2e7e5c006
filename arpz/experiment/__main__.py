"""``python -m arpz.experiment run SPEC.toml|PRESET --out DIR`` and ``report DIR``.

``run`` runs every cell not yet in DIR/results.csv (a rerun resumes), then writes the report;
``report`` rebuilds the figures and REPORT.md from results.csv alone (a results directory or a
committed results.csv), so results can be re-plotted, merged or shared without rerunning
anything.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

from arpz.experiment.presets import PRESETS
from arpz.experiment.spec import ExperimentSpec, SpecError, load_spec
from arpz.runtime.startup import add_version_option, fail

#: exit code of a run stopped by Ctrl-C / SIGTERM (finished cells are written)
INTERRUPTED = 130


def resolve_spec(name: str) -> ExperimentSpec:
    """A preset name, or a TOML file."""
    if name in PRESETS:
        return PRESETS[name]()
    if not name.endswith(".toml") and not Path(name).exists():
        raise SpecError(f"{name}: neither a preset ({', '.join(sorted(PRESETS))}) nor a spec file")
    return load_spec(name)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m arpz.experiment", description=__doc__)
    add_version_option(parser)
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run a grid (resumable) and write results and figures")
    run.add_argument("spec", help=f"a spec TOML file or a preset: {', '.join(sorted(PRESETS))}")
    run.add_argument("--out", type=Path, help="results directory (required unless --list)")
    run.add_argument("--keep-logs", action="store_true", help="keep every process log")
    run.add_argument("--list", action="store_true", help="only list the cells, run nothing")
    run.add_argument(
        "--no-merge", action="store_true", help="do not merge the runs' .rrd into all_runs.rrd"
    )
    rep = sub.add_parser("report", help="rebuild figures and REPORT.md from DIR/results.csv")
    rep.add_argument(
        "dir", type=Path, help="a results directory, or a results.csv file (e.g. a committed one)"
    )
    rep.add_argument(
        "--out", type=Path, help="where REPORT.md and figures/ go (default: the CSV's directory)"
    )
    rep.add_argument("--figures", type=Path, help="where the PNGs go (default: OUT/figures)")
    rep.add_argument(
        "--refresh",
        action="store_true",
        help="first re-derive results.csv's rows from the kept runs/*/summary.json",
    )
    args = parser.parse_args(argv)
    from arpz.experiment.report import ReportError, write_report

    if args.command == "report":
        if args.refresh:
            from arpz.experiment.results import refresh_rows

            directory = args.dir.parent if args.dir.suffix == ".csv" else args.dir
            print(f"refreshed {refresh_rows(directory)} rows from runs/*/summary.json")
        try:
            paths = write_report(args.dir, figures=args.figures, out=args.out)
        except ReportError as exc:
            return fail("experiment report", str(exc))
        for path in paths:
            print(path)
        return 0
    try:
        spec = resolve_spec(args.spec)
        from arpz.experiment.fleet import check_cells

        check_cells(spec)  # optr / optd need the optimiser's R / D: infeasible is an error now
    except SpecError as exc:
        return fail("experiment", str(exc))
    if args.list:
        for cell in spec.cells():
            print(cell.label)
        return 0
    if args.out is None:
        return fail("experiment", "run: give --out DIR, the results directory (or --list)")
    from arpz.experiment.runner import Interrupted, run_experiment

    try:
        run_experiment(spec, args.out, keep_logs=args.keep_logs)
    except Interrupted as exc:
        return fail("experiment", str(exc), INTERRUPTED)
    try:
        paths = write_report(args.out)
    except ReportError as exc:
        return fail("experiment report", str(exc), 1)
    print(f"report: {args.out / 'REPORT.md'} and {len(paths) - 1} figures", file=sys.stderr)
    if not args.no_merge:
        from arpz.experiment.recordings import MergeError, merge_recordings

        try:
            merged = merge_recordings(args.out)
        except (MergeError, OSError, subprocess.TimeoutExpired) as exc:
            print(f"recordings: not merged: {exc}", file=sys.stderr)
            return 1
        print(f"recordings: every run in {merged} (ids in rrd/index.csv)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
