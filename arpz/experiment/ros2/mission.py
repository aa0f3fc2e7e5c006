"""Figure 16 with both middlewares: the hallway mission over ROS 2 (rclpy + the RMW installed,
``mission_node``) and over arpz (``python -m arpz.experiment run`` on a one-cell lab spec), cell
by cell in fresh kernel labs with the same lab profile. Root only (the lab).

    python -m arpz.experiment.ros2.mission run --rmax 100 --depth 1 --network lab:loss-8 \\
        --repeats 1 --out /tmp/mission
    python -m arpz.experiment.ros2.mission grid --rmax 100,200,500,1000 --depths 1,1000 \\
        --configs baseline,opt --network lab:loss-8 --out /tmp/mission
    python -m arpz.experiment.ros2.mission figure --out /tmp/mission

Each cell runs ROS 2's mission, then arpz's (interleaved, so a machine whose load changes
meanwhile weighs on both alike). Progress goes to stderr; ``OUT/results.csv`` gets one row per
mission and middleware (``mission_results.COLUMNS``), ``OUT/mission.png`` the figure and
stdout the verdict table. Cells already in results.csv are skipped (a rerun resumes). arpz's
own results, runs and recordings stay under ``OUT/arpz``; the CPU seconds of its CEDDP and
robots are sampled from /proc every ``CPU_SAMPLE_S`` (the last fraction of a second is missed).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, TextIO

from arpz.experiment.ros2.mission_cell import MissionCell, row_of, run_mission
from arpz.experiment.ros2.mission_results import (
    append_row,
    arpz_row,
    draw_figure,
    error_row,
    read_rows,
    verdict_table,
)
from arpz.lab import LabError
from arpz.lab.fleet import process_cpu_s
from arpz.tools.launch import LaunchError

CPU_SAMPLE_S = 0.5
#: arpz's own runner ends a cell well within this; a backstop against a hung subprocess
ARPZ_CELL_TIMEOUT_S = 300.0


def cells_of(
    rmax: list[float],
    depths: list[int],
    configs: list[str],
    network: str,
    repeats: int,
    *,
    time_limit_s: float,
) -> list[MissionCell]:
    out = []
    for rate in rmax:
        for config in configs:
            for depth in [None] if config == "opt" else depths:
                for repeat in range(1, repeats + 1):
                    out.append(
                        MissionCell(rate, depth, config, network, repeat, time_limit_s=time_limit_s)
                    )
    return out


def cell_key(cell: MissionCell) -> dict[str, Any]:
    return {
        "rmax_hz": f"{cell.rmax_hz:g}",
        "depth": cell.depth_label,
        "config": cell.config,
        "network": cell.network,
        "repeat": cell.repeat,
    }


def _key_tuple(row: dict[str, Any]) -> tuple[str, ...]:
    return tuple(
        str(row[k]) for k in ("middleware", "rmax_hz", "depth", "config", "network", "repeat")
    )


def arpz_spec(cell: MissionCell, name: str) -> str:
    """arpz.experiment's spec (TOML) of ``cell`` alone: a lab mission cell."""
    depths = [cell.depth] if cell.depth is not None else [1]
    return (
        f'name = "{name}"\n'
        f'description = "arpz side of the ROS 2 hallway mission (arpz.experiment.ros2.mission)"\n'
        f"rmax_hz = [{cell.rmax_hz:g}]\n"
        f"depths = {depths}\n"
        f'configs = ["{cell.config}"]\n'
        f'networks = ["{cell.network}"]\n'
        f"repeats = {cell.repeat}\n"
        f"seed = {cell.seed}\n"
        "[mission]\n"
        f'world = "{cell.world}"\n'
        f"time_limit_s = {cell.time_limit_s:g}\n"
        f"max_age_s = {cell.max_age_s:g}\n"
    )


class CpuSampler:
    """CPU seconds of the processes whose command line names ``marker`` (arpz's CEDDP and
    robots, started with ``--config MARKER/runs/CELL/NAME.toml``), per config name, sampled
    from /proc until ``stop()``: the largest value seen per pid, summed per name."""

    def __init__(self, marker: str) -> None:
        self.marker = marker
        self._seen: dict[int, tuple[str, float]] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="cpu-sampler", daemon=True)

    def start(self) -> CpuSampler:
        self._thread.start()
        return self

    def stop(self) -> dict[str, float]:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5)
        return self.totals()

    def totals(self) -> dict[str, float]:
        totals: dict[str, float] = {}
        for name, cpu_s in self._seen.values():
            totals[name] = totals.get(name, 0.0) + cpu_s
        return totals

    def _run(self) -> None:
        while not self._stop.wait(CPU_SAMPLE_S):
            self.sample()

    def sample(self) -> None:
        for entry in os.scandir("/proc"):
            if not entry.name.isdigit():
                continue
            try:
                argv = Path(entry.path, "cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            text = [a.decode(errors="replace") for a in argv]
            config = next(
                (a for a in text if a.startswith(self.marker) and a.endswith(".toml")), None
            )
            if config is None or "--config" not in text:
                continue
            pid = int(entry.name)
            cpu_s = process_cpu_s(pid)
            name = Path(config).stem
            if cpu_s >= self._seen.get(pid, (name, 0.0))[1]:
                self._seen[pid] = (name, cpu_s)


def run_arpz(cell: MissionCell, out: Path, progress: TextIO) -> dict[str, Any]:
    """arpz's mission for ``cell`` through ``python -m arpz.experiment run`` (its lab cell)."""
    arpz_out = (out / "arpz").resolve()
    arpz_out.mkdir(parents=True, exist_ok=True)
    spec = arpz_out / f"spec-{cell.slug}.toml"
    spec.write_text(arpz_spec(cell, "ros2-mission-arpz"), encoding="utf-8")
    started = time.monotonic()
    sampler = CpuSampler(str(arpz_out / "runs")).start()
    try:
        done = subprocess.run(
            [sys.executable, "-m", "arpz.experiment", "run", str(spec), "--out", str(arpz_out)],
            stdout=progress,
            stderr=progress,
            timeout=ARPZ_CELL_TIMEOUT_S,
            check=False,
        )
    except subprocess.TimeoutExpired:
        sampler.stop()
        return error_row(
            "arpz", cell_key(cell), "arpz.experiment timed out", time.monotonic() - started
        )
    cpu = sampler.stop()
    wall_s = time.monotonic() - started
    key = cell_key(cell)
    for row in reversed(read_rows(arpz_out / "results.csv")):
        if all(str(row.get(k)) == str(v) for k, v in key.items()):
            return arpz_row(row, cpu, wall_s=wall_s)
    return error_row(
        "arpz", key, f"arpz.experiment exited {done.returncode} without this cell's row", wall_s
    )


def run_ros2(cell: MissionCell, out: Path, progress: TextIO) -> dict[str, Any]:
    started = time.monotonic()
    try:
        run = run_mission(cell, out / "ros2" / cell.slug, progress=progress)
    except (LaunchError, LabError) as exc:
        return error_row("ros2", cell_key(cell), str(exc)[:500], time.monotonic() - started)
    return row_of(cell, run)


def run_cells(
    cells: list[MissionCell], out: Path, middlewares: list[str], progress: TextIO
) -> None:
    out.mkdir(parents=True, exist_ok=True)
    results = out / "results.csv"
    done = {_key_tuple(r) for r in read_rows(results) if r.get("status") == "ok"}
    begun = time.monotonic()
    todo = [
        (c, m)
        for c in cells
        for m in middlewares
        if _key_tuple({**cell_key(c), "middleware": m}) not in done
    ]
    print(
        f"{len(todo)} missions to run ({len(cells)} cells x {middlewares}); results in {results}",
        file=progress,
        flush=True,
    )
    for index, (cell, middleware) in enumerate(todo, start=1):
        rate_hz, depth = cell.qos()
        print(
            f"[{index}/{len(todo)}] {middleware}: Rmax {cell.rmax_hz:g} Hz, {cell.config}, "
            f"R {rate_hz:g} Hz D {depth}, {cell.network}, repeat {cell.repeat} "
            f"({time.monotonic() - begun:.0f} s so far)",
            file=progress,
            flush=True,
        )
        row = (
            run_ros2(cell, out, progress) if middleware == "ros2" else run_arpz(cell, out, progress)
        )
        append_row(results, row)
        what = str(row.get("reason") or row.get("error"))[:160]
        print(
            f"    {middleware} {row['status']}: {row.get('verdict', '')} {what}; beams lost "
            f"{row.get('beams_lost', '')}/{row.get('beams_sent', '')}; CPU "
            f"{row.get('cpu_ceddp_s', '')} + {row.get('cpu_robots_s', '')} s; "
            f"{row.get('wall_s', '')} s",
            file=progress,
            flush=True,
        )
    print(f"done in {time.monotonic() - begun:.0f} s", file=progress, flush=True)


def report(out: Path, title: str) -> str:
    rows = read_rows(out / "results.csv")
    if rows:
        draw_figure(rows, out / "mission.png", title=title)
    return verdict_table(rows)


def _floats(text: str) -> list[float]:
    return [float(x) for x in text.split(",") if x]


def _ints(text: str) -> list[int]:
    return [int(x) for x in text.split(",") if x]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m arpz.experiment.ros2.mission")
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="one cell: ROS 2's mission and arpz's, REPEATS times")
    run.add_argument("--rmax", type=float, required=True)
    run.add_argument("--depth", type=int, default=1, help="KEEP_LAST depth (ignored with --opt)")
    run.add_argument("--opt", action="store_true", help="Opt(R) and Opt(D) of solve_closed, fixed")
    grid = sub.add_parser("grid", help="Rmax x depth x configuration")
    grid.add_argument("--rmax", type=_floats, required=True, help="e.g. 100,200,500,1000")
    grid.add_argument("--depths", type=_ints, default=[1, 1000])
    grid.add_argument("--configs", default="baseline,opt", help="baseline and/or opt")
    for p in (run, grid):
        p.add_argument("--network", default="lab:loss-8", help="lab:PROFILE on every robot's link")
        p.add_argument("--repeats", type=int, default=1)
        p.add_argument("--time-limit-s", type=float, default=60.0)
        p.add_argument("--middlewares", default="ros2,arpz", help="ros2 and/or arpz")
        p.add_argument("--out", type=Path, required=True)
    fig = sub.add_parser("figure", help="redraw OUT/mission.png and print the table")
    fig.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    title = "Hallway mission (seed 001 Fig. 16): ROS 2 (rclpy + Fast DDS, hatched) vs arpz"
    if args.command == "figure":
        print(report(args.out, title))
        return 0
    if args.command == "run":
        configs, rmax, depths = (["opt"] if args.opt else ["baseline"]), [args.rmax], [args.depth]
    else:
        configs, rmax, depths = args.configs.split(","), args.rmax, args.depths
    try:
        cells = cells_of(
            rmax, depths, configs, args.network, args.repeats, time_limit_s=args.time_limit_s
        )
    except ValueError as exc:
        parser.error(str(exc))
    middlewares = [m for m in args.middlewares.split(",") if m]
    if not middlewares or any(m not in ("ros2", "arpz") for m in middlewares):
        parser.error("--middlewares takes ros2 and/or arpz")
    try:
        run_cells(cells, args.out, middlewares, sys.stderr)
    except KeyboardInterrupt:
        print("interrupted: rerun the same command to continue", file=sys.stderr)
        return 130
    print(report(args.out, f"{title}, {args.network}"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
