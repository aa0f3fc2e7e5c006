"""One ``middleware = "ros2"`` cell: seed 001's application in rclpy (``machines_node``) in a
kernel lab of its own, over the same impaired links as arpz's lab cells.

The CEDDP node runs in the lab's ceddp namespace, robot i in robot i's, each a process of its
own. Fast DDS is set up as ``benchmarks/vs_ros2.py`` does it in the lab: a random
``ROS_DOMAIN_ID`` per cell, ``FASTDDS_BUILTIN_TRANSPORTS=UDPv4`` (every namespace shares
/dev/shm: shared memory would carry the samples past the lab's links), ``ROS_STATIC_PEERS``
(the lab's subnets are routed, no multicast between them), ``ROS_LOG_DIR`` in the cell's
directory; ``RMW_IMPLEMENTATION`` passes through from the environment.

The window: the profile is applied once every robot has matched the CEDDP and started its
timers, as arpz's lab cells apply it once every robot runs; after ``duration_s`` the links are
clean again, the CPU of every process is read (utime + stime over the window), the robots are
stopped (they wait for their samples' acknowledgements and the Hellos in flight, then write
their counters), then the CEDDP (it takes what is still arriving, then writes its own).
"""

from __future__ import annotations

import importlib.util
import json
import os
import random
import time
from pathlib import Path
from typing import Any

from arpz.experiment.fleet import configured_qos
from arpz.experiment.link_bytes import uplink_bytes
from arpz.experiment.ros2.machines_row import CellCounters
from arpz.experiment.spec import Cell, ExperimentSpec, lab_profile_name
from arpz.tools.launch import LaunchError, Proc

#: the module each process runs
NODE = "arpz.experiment.ros2.machines_node"
#: what ROS 2 needs here, and how to get it
INSTALL_HINT = "pip install 'arpz[ros2]'"
#: seconds to wait for a node's "ready" / a robot's "running" (discovery included)
START_TIMEOUT_S = 60.0
#: seconds a node may take to stop (acknowledgements, Hellos in flight, its counters)
STOP_TIMEOUT_S = 30.0


def ros2_missing() -> str | None:
    """Why ROS 2 cells cannot run here (None: rclpy and geometry_msgs import)."""
    for module in ("rclpy", "geometry_msgs"):
        try:
            found = importlib.util.find_spec(module) is not None
        except (ImportError, ValueError):
            found = False
        if not found:
            return f"ROS 2 is not installed ({module} not found): {INSTALL_HINT}"
    return None


def ros_env(domain: int, workdir: Path, peers: list[str]) -> dict[str, str]:
    """The environment of one node: its domain, UDP only, its static peers, its logs."""
    return {
        "ROS_DOMAIN_ID": str(domain),
        "FASTDDS_BUILTIN_TRANSPORTS": "UDPv4",
        "ROS_STATIC_PEERS": ";".join(peers),
        "ROS_LOG_DIR": str(workdir / "ros_log"),
        "RCUTILS_COLORIZED_OUTPUT": "0",
    }


def node_args(spec: ExperimentSpec, rate: float, depth: int, counters: Path) -> list[str]:
    return [
        "-m",
        NODE,
        "--rate-hz",
        f"{rate:g}",
        "--depth",
        str(depth),
        "--hello-rate-hz",
        f"{spec.hello_rate_hz:g}",
        "--hello-origin",
        spec.robot_names[0],
        "--hello-relay",
        spec.hello_relay,
        "--counters",
        str(counters),
    ]


def run_ros2_cell(spec: ExperimentSpec, cell: Cell, workdir: Path) -> CellCounters:
    """Run ``cell`` with ROS 2 nodes in a fresh lab; the counters of every node, the CPU and
    the lab's link counters. Raises LaunchError (ROS 2 missing, no lab, a node that failed or
    wrote no counters: the row is an error, never a silent zero)."""
    # imported here: arpz.lab brings pyroute2 and needs root
    from arpz.lab import Lab, LabError, ProfileRunner, Timeline, parse_profile

    # the lab fleet's own watch loop: a node that exits early is an error, as an arpz process
    from arpz.lab.fleet import _watch as watch
    from arpz.lab.fleet import process_cpu_s
    from arpz.lab.profiles import LinkState
    from arpz.lab.timeline import TIMELINE_FILE

    missing = ros2_missing()
    if missing is not None:
        raise LaunchError(f"{cell.slug}: {missing}")
    names = {robot: lab_profile_name(spec.robot_network(cell, robot)) for robot in spec.robot_names}
    if any(name is None for name in names.values()):
        raise LaunchError(f"{cell.slug}: ROS 2 cells run in the lab only (lab: networks)")
    profiles = {robot: parse_profile(name or "") for robot, name in names.items()}
    rate, depth = configured_qos(spec, cell)
    workdir.mkdir(parents=True, exist_ok=True)
    domain = random.randint(1, 200)
    started = time.monotonic()
    try:
        with Lab.create(spec.robot_names, timeline=Timeline(workdir / TIMELINE_FILE)) as lab:
            robot_addresses = [lab.robot(r).address for r in spec.robot_names]
            ceddp = lab.spawn(
                "ceddp",
                lab.ceddp_namespace,
                [
                    *node_args(spec, rate, depth, workdir / "ceddp.json"),
                    "--role",
                    "ceddp",
                    "--robots",
                    ",".join(
                        f"{r}={p}" for r, p in zip(spec.robot_names, spec.presets, strict=True)
                    ),
                ],
                workdir,
                env=ros_env(domain, workdir, robot_addresses),
            )
            ceddp.wait_line("ready", START_TIMEOUT_S)
            robots: list[Proc] = []
            for index, robot in enumerate(spec.robot_names):
                args = [
                    *node_args(spec, rate, depth, workdir / f"{robot}.json"),
                    "--role",
                    "robot",
                    "--name",
                    robot,
                    "--preset",
                    spec.presets[index],
                    # arpz's robot seed for this robot (arpz.experiment.fleet.cell_fleet)
                    "--seed",
                    str(spec.seed * 100 + index + 1),
                ]
                robots.append(
                    lab.spawn(
                        robot,
                        lab.robot(robot).namespace,
                        args,
                        workdir,
                        env=ros_env(domain, workdir, [lab.ceddp_address]),
                    )
                )
            for proc in robots:
                proc.wait_line("running", START_TIMEOUT_S)
            procs = [ceddp, *robots]
            cpu0 = {p.name: process_cpu_s(p.popen.pid) for p in procs}
            runner = ProfileRunner(
                lab, profiles, seed=spec.seed + cell.repeat, horizon_s=spec.duration_s
            )
            window_start = time.monotonic()
            runner.start()
            try:
                with open(workdir / "lab.log", "w", encoding="utf-8") as progress:
                    watch(lab, procs, spec.duration_s, progress, lambda: False)
            finally:
                runner.stop()
            measured = time.monotonic() - window_start
            for name, link in lab.robots.items():
                lab.apply(name, LinkState(subnet=link.state.subnet), "end of the run: clean links")
            cpu = {p.name: process_cpu_s(p.popen.pid) - cpu0[p.name] for p in procs}
            counters = {name: lab.counters(name) for name in lab.robots}
            bytes_up = uplink_bytes(lab)
            failures = [_stop(proc) for proc in robots]
            failures.append(_stop(ceddp))
            problems = [f for f in failures if f]
            if problems:
                raise LaunchError(f"{cell.slug}: " + "; ".join(problems))
    except LabError as exc:
        raise LaunchError(f"{cell.slug}: the lab: {exc}") from exc
    nodes = {"ceddp": _counters(workdir / "ceddp.json")}
    for robot in spec.robot_names:
        nodes[robot] = _counters(workdir / f"{robot}.json")
    return CellCounters(
        nodes=nodes,
        cpu_s=cpu,
        link_seen=sum(c.up_seen + c.down_seen for c in counters.values()),
        link_dropped=sum(c.up_dropped + c.down_dropped for c in counters.values()),
        bytes_up=bytes_up,
        measured_s=measured,
        wall_s=time.monotonic() - started,
        rate_hz=rate,
        depth=depth,
    )


def _stop(proc: Proc) -> str | None:
    """SIGINT and wait: None if it ended cleanly, else what went wrong."""
    try:
        code = proc.stop(STOP_TIMEOUT_S)
    except LaunchError as exc:
        return str(exc)
    if code != 0:
        return f"{proc.name} exited with code {code}: {' '.join(proc.tail(6).split())}"
    return None


def _counters(path: Path) -> dict[str, Any]:
    try:
        data: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise LaunchError(f"{path.name}: no counters from the node ({exc})") from None
    return data


def rmw() -> str:
    """The RMW the nodes use (Fast DDS unless RMW_IMPLEMENTATION says otherwise)."""
    return os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
