"""One hallway mission over ROS 2 in a fresh kernel lab: the planner node in the lab's CEDDP
namespace, robot i's node in robot i's namespace, the cell's lab profile on every robot's link
(as arpz's lab cells: ``arpz.experiment.runner._run_in_lab``, ``arpz.lab.fleet``).

Fast DDS is set up as ``benchmarks/vs_ros2.py`` does: a random ``ROS_DOMAIN_ID``,
``FASTDDS_BUILTIN_TRANSPORTS=UDPv4`` (every namespace shares /dev/shm: shared memory would carry
the samples past the lab's links, so the row records the frames the links saw), the lab's
subnets routed without multicast so discovery goes to ``ROS_STATIC_PEERS`` (the planner: every
robot; a robot: the CEDDP's address), ``RMW_IMPLEMENTATION`` inherited, ``ROS_LOG_DIR`` in the
cell's directory. The profile starts once the planner has every robot's pose (the mission's
start), as arpz's lab cells start it once every robot runs.
"""

from __future__ import annotations

import json
import random
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

from arpz.ceddp.optimiser import QosLimits, solve_closed
from arpz.experiment.ros2.mission_parts import MISSION_TOPICS_PER_ROBOT, verdict_letter
from arpz.lab import Lab, LinkState, ProfileRunner, Timeline, parse_profile
from arpz.lab.timeline import TIMELINE_FILE
from arpz.mission import World
from arpz.tools.launch import LaunchError, Proc

NODE_MODULE = "arpz.experiment.ros2.mission_node"
#: seed 001's bounds of the optimiser (Table 2) and arpz.experiment.spec's defaults
RMIN_HZ = 1.0
DMAX = 5000
#: seconds for a node to print ``ready`` (rclpy's import and Fast DDS's participant)
READY_TIMEOUT_S = 60.0
#: seconds for the mission to start (every robot's pose at the planner) once the nodes run
START_TIMEOUT_S = 60.0
#: after the time limit, how long to wait for the verdict before ending the cell
VERDICT_MARGIN_S = 15.0
STOP_TIMEOUT_S = 20.0


@dataclass(frozen=True)
class MissionCell:
    """One point of Figure 16's grid: Rmax, the fixed KEEP_LAST depth (None with OPT, whose
    depth is Opt(D)), the configuration ("baseline" or "opt"), the lab network and a repeat."""

    rmax_hz: float
    depth: int | None
    config: str
    network: str
    repeat: int = 1
    world: str = "hallway_small"
    time_limit_s: float = 60.0
    max_age_s: float = 0.3
    seed: int = 1
    command_acks: str = "none"

    def __post_init__(self) -> None:
        if self.config not in ("baseline", "opt"):
            raise ValueError(f"config must be baseline or opt, got {self.config!r}")
        if (self.config == "opt") != (self.depth is None):
            raise ValueError("a baseline cell needs a depth; an opt cell takes Opt(D) (depth None)")
        if not self.network.startswith("lab:"):
            raise ValueError(
                f"ROS 2 missions run in the kernel lab: network 'lab:PROFILE', got {self.network!r}"
            )
        parse_profile(self.profile)  # ValueError naming the profiles

    @property
    def profile(self) -> str:
        return self.network.removeprefix("lab:")

    @property
    def depth_label(self) -> str:
        """How arpz.experiment's results.csv writes the depth: the number, or "opt"."""
        return "opt" if self.depth is None else str(self.depth)

    @property
    def slug(self) -> str:
        return f"r{self.rmax_hz:g}_d{self.depth_label}_{self.config}_{self.profile}_{self.repeat}"

    def robots(self) -> list[str]:
        return list(World.load(self.world).robots)

    def qos(self) -> tuple[float, int]:
        """(rate, depth) of the beams: Rmax and the cell's depth, or with OPT the optimiser's
        Opt(R) and Opt(D) for the fleet (``solve_closed``, as arpz's CEDDP solves it), applied
        fixed for the run as seed 001 did."""
        if self.depth is not None:
            return self.rmax_hz, self.depth
        solution = solve_closed(
            QosLimits(rmax_hz=self.rmax_hz, rmin_hz=RMIN_HZ, dmax=DMAX),
            [MISSION_TOPICS_PER_ROBOT] * len(self.robots()),
        )
        return float(solution.rate_hz), int(solution.depth)


def ros_env(workdir: Path, domain: int, static_peers: list[str]) -> dict[str, str]:
    """Fast DDS over the lab's links only: UDPv4, no shared memory, unicast discovery."""
    return {
        "ROS_DOMAIN_ID": str(domain),
        "ROS_LOG_DIR": str(workdir / "ros_log"),
        "RCUTILS_COLORIZED_OUTPUT": "0",
        "FASTDDS_BUILTIN_TRANSPORTS": "UDPv4",
        "ROS_STATIC_PEERS": ";".join(static_peers),
    }


def node_args(
    cell: MissionCell, role: str, out: Path, *, robot: str = "", seed: int = 0
) -> list[str]:
    rate_hz, depth = cell.qos()
    args = ["-m", NODE_MODULE, "--role", role, "--world", cell.world]
    args += ["--rate-hz", f"{rate_hz:g}", "--depth", str(depth), "--out", str(out)]
    if role == "robot":
        return [*args, "--robot", robot, "--seed", str(seed)]
    return [
        *args,
        "--time-limit-s",
        f"{cell.time_limit_s:g}",
        "--max-age-s",
        f"{cell.max_age_s:g}",
        "--command-acks",
        cell.command_acks,
    ]


@dataclass
class MissionRun:
    """What the nodes reported, and the links' frames seen and dropped."""

    planner: dict[str, Any]
    robots: dict[str, dict[str, Any]]
    links: dict[str, dict[str, int]]
    wall_s: float


def run_mission(
    cell: MissionCell,
    workdir: Path,
    *,
    progress: TextIO = sys.stderr,
    until_s: float | None = None,
) -> MissionRun:
    """Run the cell's mission to its verdict (or ``until_s`` seconds after its start: a
    bounded slice) and return the reports. Raises LaunchError when a node fails or the mission
    never starts, LabError when the lab cannot run it."""
    robots = cell.robots()
    workdir.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    domain = random.randint(1, 100)
    with Lab.create(robots, timeline=Timeline(workdir / TIMELINE_FILE)) as lab:
        addresses = [lab.robot(r).address for r in robots]
        planner = lab.spawn(
            "planner",
            lab.ceddp_namespace,
            node_args(cell, "planner", workdir / "planner.json"),
            workdir,
            env=ros_env(workdir, domain, addresses),
        )
        nodes: dict[str, Proc] = {}
        for index, robot in enumerate(robots, start=1):
            nodes[robot] = lab.spawn(
                robot,
                lab.robot(robot).namespace,
                node_args(
                    cell,
                    "robot",
                    workdir / f"{robot}.json",
                    robot=robot,
                    seed=cell.seed * 100 + index,
                ),
                workdir,
                env=ros_env(workdir, domain, [lab.ceddp_address]),
            )
        for proc in [planner, *nodes.values()]:
            proc.wait_line("ready", timeout_s=READY_TIMEOUT_S)
        _wait(planner, [planner, *nodes.values()], "mission started", START_TIMEOUT_S)
        print(f"    {cell.slug}: ROS 2 mission started", file=progress, flush=True)
        limit_s = cell.time_limit_s + VERDICT_MARGIN_S if until_s is None else until_s
        runner = ProfileRunner(
            lab,
            {r: parse_profile(cell.profile) for r in robots},
            seed=cell.seed + cell.repeat,
            horizon_s=limit_s,
        )
        runner.start()
        try:
            _wait(
                planner,
                [planner, *nodes.values()],
                "mission verdict",
                limit_s,
                must=until_s is None,
            )
        finally:
            runner.stop()
        for robot, link in lab.robots.items():
            lab.apply(robot, LinkState(subnet=link.state.subnet), "end of the mission: clean links")
        counters = {robot: lab.counters(robot) for robot in robots}
        if planner.has_line("mission verdict"):  # the planner sends STOP to every robot now
            failures = [_stop(proc) for proc in nodes.values()]
            time.sleep(1.0)  # the samples still on their way to the planner
            failures.append(_stop(planner))
        else:
            # a slice: the planner first (its judge ends it "incomplete"), or it drives the
            # fleet on while the robots stopped first stand still, and the judge sees collisions
            failures = [_stop(planner), *(_stop(proc) for proc in nodes.values())]
    problems = [f for f in failures if f]
    if problems:
        raise LaunchError("; ".join(problems))
    return MissionRun(
        planner=_load(workdir / "planner.json"),
        robots={robot: _load(workdir / f"{robot}.json") for robot in robots},
        links={
            robot: {
                "up_seen": c.up_seen,
                "up_dropped": c.up_dropped,
                "down_seen": c.down_seen,
                "down_dropped": c.down_dropped,
            }
            for robot, c in counters.items()
        },
        wall_s=time.monotonic() - started,
    )


def _wait(
    watch: Proc, procs: list[Proc], line: str, timeout_s: float, *, must: bool = True
) -> None:
    """Poll for ``line`` from ``watch``; a node that exits meanwhile is an error."""
    deadline = time.monotonic() + timeout_s
    while not watch.has_line(line):
        for proc in procs:
            if proc.popen.poll() is not None:
                raise LaunchError(
                    f"{proc.name} exited early ({proc.popen.returncode}): {proc.tail(8)}"
                )
        if time.monotonic() > deadline:
            if must:
                raise LaunchError(f"no {line!r} from {watch.name} within {timeout_s:.0f} s")
            return
        time.sleep(0.1)


def _stop(proc: Proc) -> str:
    try:
        code = proc.stop(STOP_TIMEOUT_S)
    except LaunchError as exc:
        return str(exc)
    return "" if code == 0 else f"{proc.name} exited with code {code}: {proc.tail(8)}"


def _load(path: Path) -> dict[str, Any]:
    try:
        data: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise LaunchError(f"no report in {path}: {exc}") from None
    return data


def row_of(cell: MissionCell, run: MissionRun) -> dict[str, Any]:
    """The results row of a ROS 2 mission (``arpz.experiment.ros2.mission_results.COLUMNS``)."""
    rate_hz, depth = cell.qos()
    planner, robots = run.planner, run.robots
    result = planner.get("result") or {}
    sent = sum(int(r["beams_sent"]) for r in robots.values())
    received = sum(int(n) for n in planner["beams_received"].values())
    latency = planner.get("beam_latency_ms") or {}
    row: dict[str, Any] = {
        "middleware": "ros2",
        "rmax_hz": f"{cell.rmax_hz:g}",
        "depth": cell.depth_label,
        "config": cell.config,
        "network": cell.network,
        "repeat": cell.repeat,
        "status": "ok",
        "rate_hz": f"{rate_hz:g}",
        "qos_depth": depth,
        "verdict": verdict_letter(result),
        "mission": result.get("mission", "failure"),
        "reason": result.get("reason", "no verdict: the mission never started"),
        "duration_s": result.get("duration_s", ""),
        "beams_sent": sent,
        "beams_received": received,
        "beams_lost": sent - received,
        "beam_loss_pct": round(100.0 * (sent - received) / sent, 2) if sent else "",
        "beams_due": sum(int(r["beams_due"]) for r in robots.values()),
        "beam_write_failures": sum(int(r.get("beam_write_failures", 0)) for r in robots.values()),
        "beam_latency_ms_p50": latency.get("p50", ""),
        "beam_latency_ms_p99": latency.get("p99", ""),
        "commands_sent": planner["commands_sent"],
        "commands_received": sum(int(r["commands_received"]) for r in robots.values()),
        "watchdog_stops": sum(int(r["watchdog_stops"]) for r in robots.values()),
        "link_frames": sum(c["up_seen"] + c["down_seen"] for c in run.links.values()),
        "link_dropped": sum(c["up_dropped"] + c["down_dropped"] for c in run.links.values()),
        "cpu_ceddp_s": planner["cpu_s"],
        "cpu_robots_s": round(sum(float(r["cpu_s"]) for r in robots.values()), 3),
        "wall_s": round(run.wall_s, 1),
        "error": "",
    }
    return row
