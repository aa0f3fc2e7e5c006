"""The configs of one cell: what a user would write to run that point of seed 001's grid by hand.

Every robot connects through its own emulated link (an ``arpz.netem`` proxy in front of the
CEDDP's UDP endpoint). Without OPT the sensors publish at Rmax per topic (seed 001: "DEADLINE
Rmax") with the cell's fixed KEEP_LAST depth; with OPT the CEDDP's optimiser assigns R and D
(Opt(R), Opt(D)) and the robots apply them in place.
"""

from __future__ import annotations

from typing import Any

from arpz.ceddp.optimiser import InvalidQosInput, OptimiserError, QosLimits, solve_closed
from arpz.experiment.spec import OPT_DEPTH, Cell, ExperimentSpec, has_feature, has_opt
from arpz.launch import FleetSpec
from arpz.robot.sensors.presets import PRESETS

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


def start_rate(spec: ExperimentSpec, cell: Cell) -> float:
    """The publish rate robots start with: Rmax without OPT; with OPT the optimiser's R for the
    whole fleet, so the window measures the optimised steady state rather than a start-up burst
    at Rmax (the CEDDP's own assignment, recorded in results.csv, replaces it within a second)."""
    if not has_opt(cell.config):
        return cell.rmax_hz
    try:
        limits = QosLimits(rmax_hz=cell.rmax_hz, rmin_hz=spec.rmin_hz, dmax=spec.dmax)
        return float(solve_closed(limits, topic_counts(spec)).rate_hz)
    except (OptimiserError, InvalidQosInput):
        return cell.rmax_hz


def cell_fleet(
    spec: ExperimentSpec, cell: Cell, *, listen: list[str], robot_connect: dict[str, str], rrd: str
) -> FleetSpec:
    """The CEDDP and robot configs (dicts in arpz.config's TOML schema) of ``cell``."""
    depth = INITIAL_OPT_DEPTH if cell.depth == OPT_DEPTH else int(cell.depth)
    channel = {"reliability": "reliable", "history": "keep_last", "depth": depth}
    ceddp: dict[str, Any] = {
        "fleet": "exp",
        "listen": listen,
        "rrd": rrd,
        "cache_control": has_feature(cell.config, "cc"),
        "sensor_qos": channel,
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
    rate = start_rate(spec, cell)
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
