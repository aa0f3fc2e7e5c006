"""The configs of one cell: what a user would write to run that point of seed 001's grid by hand.

An arpz cell: every robot connects through its own emulated link (an ``arpz.netem`` proxy in front
of the CEDDP's UDP endpoint). Without OPT the sensors publish at Rmax per topic (seed 001: "DEADLINE
Rmax") with the cell's fixed KEEP_LAST depth; with OPT the CEDDP's optimiser assigns R and D
(Opt(R), Opt(D)) and the robots apply them in place. ``optr`` and ``optd`` apply only one of the
two: the CEDDP's optimiser is off, and the robots are configured with the optimiser's R (at the
cell's fixed depth) or its D (at Rmax), computed here as the CEDDP would (``solve_closed``, the
"paper" depth policy, the topic counts the robots announce). A ROS 2 cell runs at the same (rate,
depth), ``configured_qos``, with OPT's R and D both fixed for the run.
"""

from __future__ import annotations

from typing import Any

from arpz.ceddp.optimiser import (
    InvalidQosInput,
    OptimiserError,
    QosLimits,
    QosSolution,
    solve_closed,
)
from arpz.core.config import ConfigError, TrafficQos, from_dict
from arpz.experiment.spec import (
    OPT_DEPTH,
    Cell,
    ExperimentSpec,
    SpecError,
    has_feature,
    has_opt,
    opt_depth,
    opt_rate,
)
from arpz.robot.sensors.presets import PRESETS
from arpz.tools.launch import FleetSpec

#: the KEEP_LAST depth OPT robots start with until the first assignment (ROS 2's default)
INITIAL_OPT_DEPTH = 10
#: the 8 LIDAR beams of seed 001 section 3.2
SIM_BEAMS = 8


def topic_counts(spec: ExperimentSpec) -> list[int]:
    """T_a per robot as the robots announce it to the CEDDP (eq. 1): the sensor topics plus
    the command topic; a simulated robot also has its telemetry topic."""
    if spec.mission is not None:
        return [SIM_BEAMS + 2 for _ in spec.robot_names]
    return [len(PRESETS[p]) + 1 for p in spec.presets]


def optimiser_solution(spec: ExperimentSpec, rmax_hz: float) -> QosSolution:
    """Problem (6) for the whole fleet at ``rmax_hz``, as the CEDDP's optimiser solves it once
    every robot has announced its topics. Raises OptimiserError (infeasible or invalid)."""
    limits = QosLimits(rmax_hz=rmax_hz, rmin_hz=spec.rmin_hz, dmax=spec.dmax)
    return solve_closed(limits, topic_counts(spec))


def start_rate(spec: ExperimentSpec, cell: Cell) -> float:
    """The publish rate robots start with: Rmax without OPT; with OPT the optimiser's R for the
    whole fleet, so the window measures the optimised steady state rather than a start-up burst
    at Rmax (the CEDDP's own assignment, recorded in results.csv, replaces it within a second);
    with optr the optimiser's R for the whole run."""
    if not opt_rate(cell.config):
        return cell.rmax_hz
    try:
        return float(optimiser_solution(spec, cell.rmax_hz).rate_hz)
    except (OptimiserError, InvalidQosInput) as exc:
        if has_opt(cell.config) and cell.middleware == "arpz":
            return cell.rmax_hz  # the CEDDP reports the same error and assigns nothing
        raise SpecError(f"{cell.label}: no Opt(R) to run at: {exc}") from None


def start_depth(spec: ExperimentSpec, cell: Cell) -> int:
    """The KEEP_LAST depth of robots and CEDDP: the cell's fixed depth; with OPT the depth the
    robots hold until the CEDDP's first assignment; with optd, and with OPT on ROS 2 (which
    seed 001 configured with the R and D CVXPY computed offline), the optimiser's D, fixed."""
    if has_opt(cell.config) and cell.middleware == "arpz":
        return INITIAL_OPT_DEPTH
    if opt_depth(cell.config):
        try:
            return int(optimiser_solution(spec, cell.rmax_hz).depth)
        except (OptimiserError, InvalidQosInput) as exc:
            raise SpecError(f"{cell.label}: no Opt(D) to run at: {exc}") from None
    if cell.depth == OPT_DEPTH:
        raise SpecError(f"{cell.label}: depth {OPT_DEPTH!r} without opt or optd")
    return int(cell.depth)


def configured_qos(spec: ExperimentSpec, cell: Cell) -> tuple[float, int]:
    """(rate, depth) the robots run at when no CEDDP assignment replaces them (all but opt):
    what results.csv records as the QoS used. Raises SpecError when the optimiser cannot give
    optr's R or optd's D."""
    return start_rate(spec, cell), start_depth(spec, cell)


def check_cells(spec: ExperimentSpec) -> None:
    """Raise SpecError naming the first cell whose configs cannot be made (before any runs),
    or when ROS 2 cells are asked for and ROS 2 is not installed."""
    for cell in spec.cells():
        configured_qos(spec, cell)
    check_traffic(spec)
    if "ros2" in spec.middlewares:
        from arpz.experiment.ros2.machines_cell import ros2_missing

        missing = ros2_missing()
        if missing is not None:
            raise SpecError(f"{spec.name}: middleware ros2: {missing}")


def check_traffic(spec: ExperimentSpec) -> None:
    """Raise SpecError when ``[traffic]`` names what arpz.core.config's TrafficQos does not take."""
    unknown = sorted(set(spec.traffic) - set(TrafficQos.__struct_fields__))
    if "sensor_qos" in spec.traffic:
        raise SpecError("[traffic] cannot set sensor_qos: the grid's depths and configs set it")
    if unknown:
        raise SpecError(
            f"[traffic] takes the traffic keys of both configs "
            f"({', '.join(TrafficQos.__struct_fields__)}), not {', '.join(unknown)}"
        )
    try:
        from_dict(spec.traffic, TrafficQos, source="[traffic]")
    except ConfigError as exc:
        raise SpecError(str(exc)) from None


def cell_fleet(
    spec: ExperimentSpec, cell: Cell, *, listen: list[str], robot_connect: dict[str, str], rrd: str
) -> FleetSpec:
    """The CEDDP and robot configs (dicts in arpz.core.config's TOML schema) of ``cell``."""
    rate, depth = configured_qos(spec, cell)
    channel = {"reliability": "reliable", "history": "keep_last", "depth": depth}
    ceddp: dict[str, Any] = {
        "fleet": "exp",
        "listen": listen,
        "rrd": rrd,
        "cache_control": has_feature(cell.config, "cc"),
        "sensor_qos": channel,
        **spec.traffic,
    }
    if has_opt(cell.config):
        ceddp["qos"] = {
            "enabled": True,
            "rmax_hz": cell.rmax_hz,
            "rmin_hz": spec.rmin_hz,
            "dmax": spec.dmax,
        }
    mission = spec.mission
    if mission is not None:
        ceddp["mission"] = {
            "world": mission.world,
            "time_limit_s": mission.time_limit_s,
            "max_age_s": mission.max_age_s,
        }
    else:
        ceddp["hello"] = {"relay": spec.hello_relay}
    robots: dict[str, dict[str, Any]] = {}
    for index, robot in enumerate(spec.robot_names):
        conf: dict[str, Any] = {
            "robot_id": robot,
            "fleet": "exp",
            "connect": [robot_connect[robot]],
            "seed": spec.seed * 100 + index + 1,
            "local_cache": {
                "enabled": has_feature(cell.config, "lc"),
                "max_silence_s": spec.local_cache_max_silence_s,
            },
            "sensor_qos": channel,
            "match_timeout_s": 15.0,
            **spec.traffic,
        }
        if mission is not None:
            conf["sim"] = {"world": mission.world, "beam_rate_hz": rate}
        else:
            conf["preset"] = spec.presets[index]
            conf["preset_rate_hz"] = rate
            if index == 0:
                conf["hello"] = {"enabled": True, "rate_hz": spec.hello_rate_hz}
        robots[robot] = conf
    # the Hello relay is up before the origin (a Hello sent before it joined cannot be relayed)
    first = (spec.hello_relay,) if mission is None and spec.hello_relay in robots else ()
    return FleetSpec(ceddp=ceddp, robots=robots, first=first)
