"""``python -m arpz demo``: a CEDDP and N robots as real processes on loopback.

The demo writes real TOML configs, starts ``python -m arpz.ceddp`` and ``python -m arpz.robot``
exactly as a user would on a server and on robots, runs them, stops them with SIGINT (the
clean path), then prints the reconciled summary and the path of the ``.rrd``. Any part that
fails (a process that does not start, does not stop, exits non-zero, or never reports) makes
the demo exit non-zero with a message that says which and where its log is.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

from arpz.core.errors import ArpzError
from arpz.runtime.startup import (
    JSON_TO_STDOUT,
    add_json_option,
    add_version_option,
    emit_json,
    fail,
)
from arpz.tools.launch import FleetSpec, LaunchError, Proc, free_port, on_fresh_ports, run_fleet

PRESET_CYCLE = ("machine1", "machine2", "machine3")
#: exit code of a mission that ran and failed (as opposed to 1: the demo itself failed)
MISSION_FAILED = 3


class DemoError(ArpzError, RuntimeError):
    pass


@dataclass(frozen=True)
class DemoOptions:
    robots: int = 3
    duration_s: float = 10.0
    rrd: Path = Path("arpz-demo.rrd")
    rate_hz: float = 50.0
    hello_rate_hz: float = 10.0
    local_cache: bool = True
    cache_control: bool = True
    #: QoS balancing optimiser on with this Rmax (0: off, sensors keep rate_hz)
    rmax_hz: float = 0.0
    #: "hallway": run seed 001's mission (3 simulated robots) instead of the sensor demo
    mission: str | None = None
    world: str = "hallway"
    #: the reliable channel for sensor topics: "reliable", "best_effort", or "none" (plain Zenoh)
    reliability: str = "reliable"
    history: str = "keep_last"
    #: KEEP_LAST depth until the QoS optimiser assigns one
    depth: int = 10


def demo_spec(options: DemoOptions, endpoint: str) -> FleetSpec:
    """The configs a user would write for this demo, as dicts."""
    mission = options.mission is not None
    robots = 3 if mission else options.robots
    ceddp: dict[str, Any] = {
        "fleet": "demo",
        "listen": [endpoint],
        "rrd": options.rrd.as_posix(),
        "cache_control": options.cache_control,
        "hello": {"relay": f"robot{robots}"} if robots > 1 and not mission else {},
    }
    if options.rmax_hz > 0:
        ceddp["qos"] = {"enabled": True, "rmax_hz": options.rmax_hz}
    channel: dict[str, Any] | None = None
    if options.reliability == "none":
        ceddp["reliability"] = "none"
    else:
        channel = {
            "reliability": options.reliability,
            "history": options.history,
            "depth": options.depth,
        }
        ceddp["sensor_qos"] = channel
    if mission:
        ceddp["mission"] = {"world": options.world, "time_limit_s": options.duration_s}
    fleet: dict[str, dict[str, Any]] = {}
    for index in range(1, robots + 1):
        conf: dict[str, Any] = {
            "robot_id": f"robot{index}",
            "fleet": "demo",
            "connect": [endpoint],
            "seed": index,
            "local_cache": {"enabled": options.local_cache},
        }
        if channel is not None:
            conf["sensor_qos"] = channel
        else:
            conf["reliability"] = "none"
        if mission:
            conf["sim"] = {"world": options.world, "beam_rate_hz": options.rate_hz}
        else:
            conf["preset"] = PRESET_CYCLE[(index - 1) % 3]
            conf["preset_rate_hz"] = options.rate_hz
            if index == 1:
                conf["hello"] = {"enabled": True, "rate_hz": options.hello_rate_hz}
        fleet[f"robot{index}"] = conf
    # the Hello relay (the last robot) is up before the origin: a Hello sent before its relay
    # joined cannot be relayed (the CEDDP counts it as no_relay)
    return FleetSpec(ceddp=ceddp, robots=fleet, first=(f"robot{robots}",))


def run_demo(options: DemoOptions, workdir: Path, progress: TextIO = sys.stderr) -> dict[str, Any]:
    """Run the fleet and return the CEDDP's summary; raise DemoError when a part failed."""

    def mission_over(ceddp: Proc) -> bool:
        return ceddp.has_line("arpz.ceddp: mission ")

    def start() -> tuple[FleetSpec, dict[str, Any]]:
        spec = demo_spec(options, f"tcp/127.0.0.1:{free_port()}")
        summary = run_fleet(
            spec,
            workdir,
            # a mission ends with its verdict; the time limit is the judge's, plus a margin
            duration_s=options.duration_s + (30 if options.mission else 0),
            until=mission_over if options.mission else None,
            progress=progress,
            label="demo",
        )
        return spec, summary

    try:
        spec, summary = on_fresh_ports(start, lambda why: print(f"demo: {why}", file=progress))
    except LaunchError as exc:
        raise DemoError(str(exc)) from None
    failures = check_summary(summary, len(spec.robots), hello=options.mission is None)
    if failures:
        print(format_summary(summary), file=progress)
        raise DemoError("; ".join(failures))
    return summary


def check_summary(summary: dict[str, Any], robots: int, *, hello: bool = True) -> list[str]:
    """What a healthy demo must show: every robot reported, counts reconcile, Hellos came back."""
    problems = []
    for index in range(1, robots + 1):
        name = f"robot{index}"
        row = summary["robots"].get(name)
        if row is None:
            problems.append(f"{name} never reached the CEDDP")
            continue
        if not row["final_stats"]:
            problems.append(f"{name}'s final report did not reach the CEDDP")
        accounted = row["sent"] + row["held_back"] + row["write_failures"] + row["driver_errors"]
        if row["produced"] != accounted:
            problems.append(
                f"{name}: produced {row['produced']} != sent {row['sent']} + held back "
                f"{row['held_back']} + refused by a full history {row['write_failures']} + "
                f"driver errors {row['driver_errors']}"
            )
        if row["sent"] != row["received"] + row["lost"]:
            problems.append(
                f"{name}: sent {row['sent']} != received {row['received']} + lost {row['lost']}"
            )
    if hello and not (summary["robots"].get("robot1", {}).get("hello") or {}).get("received"):
        problems.append("no Hello came back to robot1")
    return problems


def _fmt(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.2f}"
    return str(value)


def format_summary(summary: dict[str, Any]) -> str:
    headers = [
        "robot",
        "produced",
        "sent",
        "held back",
        "received",
        "cc discarded",
        "lost",
        "lat p50 ms",
        "lat p99 ms",
    ]
    rows = [
        [
            name,
            *(
                _fmt(r[k])
                for k in (
                    "produced",
                    "sent",
                    "held_back",
                    "received",
                    "cc_discarded",
                    "lost",
                    "latency_ms_p50",
                    "latency_ms_p99",
                )
            ),
        ]
        for name, r in sorted(summary["robots"].items())
    ]
    widths = [
        max(len(h), *(len(row[i]) for row in rows)) if rows else len(h)
        for i, h in enumerate(headers)
    ]
    lines = ["  ".join(h.rjust(w) for h, w in zip(headers, widths, strict=True))]
    lines += ["  ".join(c.rjust(w) for c, w in zip(row, widths, strict=True)) for row in rows]
    for name, r in sorted(summary["robots"].items()):
        hello = r.get("hello")
        if hello and hello.get("sent"):
            lines.append(
                f"Hello {name} -> CEDDP -> relay -> CEDDP -> {name}: sent {hello['sent']}, "
                f"back {hello['received']}, lost {hello['lost']}"
                f" ({summary['hello_relay']['no_relay']} before the relay joined), "
                f"late {hello['late']}, "
                f"round trip p50 {_fmt(hello['rtt_ms_p50'])} ms, p99 {_fmt(hello['rtt_ms_p99'])} ms"
            )
    qos = summary.get("qos")
    if qos:
        for assignment in qos["assignments"]:
            robots = assignment["robots"]
            first = next(iter(robots.values()))
            lines.append(
                f"QoS epoch {assignment['epoch']} ({assignment['reason']}): "
                f"T_avg {assignment['t_avg']:.3f}, R {first['rate_hz']:.2f} Hz "
                f"(deadline {first['deadline_s'] * 1000:.1f} ms), D {first['depth']} "
                f"for {', '.join(robots)}"
            )
        acks = ", ".join(
            f"{robot} {ack['status']} epoch {ack['epoch']}" for robot, ack in qos["acks"].items()
        )
        lines.append(f"QoS acknowledgements: {acks or 'none'}")
        for error in qos["errors"]:
            lines.append(f"QoS error: {error}")
    ingest = summary["ingest"]
    lines.append(
        f"CEDDP: {ingest['processed']} samples ingested, "
        f"{ingest['unknown_keys']} on unknown keys, "
        f"{summary['dashboard']['dropped']} dashboard frames dropped"
    )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m arpz demo", description=__doc__)
    parser.add_argument("--robots", type=int, default=3, help="sensor demo only (missions: 3)")
    parser.add_argument(
        "--duration", type=float, help="seconds of running; for a mission, its time limit"
    )
    parser.add_argument(
        "--rrd",
        type=Path,
        help="the Rerun recording (default: arpz-demo.rrd in --workdir, else in the current "
        "directory; the previous demo's recording there is replaced)",
    )
    parser.add_argument(
        "--rate",
        type=float,
        help="sensor (mission: LIDAR beam) rate in Hz; giving it forces the rate "
        "(no QoS optimiser unless --rmax is given too)",
    )
    parser.add_argument("--hello-rate", type=float, default=10.0, help="Hello rate (Hz)")
    parser.add_argument("--no-local-cache", action="store_true")
    parser.add_argument("--no-cache-control", action="store_true")
    parser.add_argument("--rmax", type=float, help="QoS balancing optimiser Rmax (Hz), eq. 4")
    parser.add_argument("--no-qos", action="store_true", help="no QoS optimiser")
    parser.add_argument(
        "--reliability",
        choices=["reliable", "best_effort", "none"],
        default="reliable",
        help="sensor topics through arpz's reliable channel (or plain Zenoh: none)",
    )
    parser.add_argument("--history", choices=["keep_last", "keep_all"], default="keep_last")
    parser.add_argument(
        "--depth", type=int, default=10, help="KEEP_LAST depth (the QoS optimiser may change it)"
    )
    parser.add_argument("--mission", choices=["hallway"], help="run seed 001's hallway mission")
    parser.add_argument("--world", default="hallway", help="mission map: hallway, hallway_small")
    parser.add_argument("--workdir", type=Path, help="where configs and logs go (default: temp)")
    add_json_option(parser, "the summary (a mission's result and summary)")
    add_version_option(parser)
    args = parser.parse_args(argv)
    mission = args.mission is not None
    duration = args.duration if args.duration is not None else (150.0 if mission else 10.0)
    rate = args.rate if args.rate is not None else (20.0 if mission else 50.0)
    forced = args.rate is not None and args.rmax is None
    rmax = 0.0 if (args.no_qos or forced) else (args.rmax or 500.0)
    if args.robots < 1 or duration <= 0 or rate <= 0 or args.depth < 1:
        return fail("demo", "--robots and --depth must be >= 1, --duration and --rate > 0")
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="arpz-demo-"))
    rrd = args.rrd or (args.workdir or Path.cwd()) / "arpz-demo.rrd"
    # the demo's own output from its last run: replaced, not kept beside (a server keeps every
    # earlier recording, a demo run again and again would fill the directory)
    if args.rrd is None:
        rrd.unlink(missing_ok=True)
    options = DemoOptions(
        robots=args.robots,
        duration_s=duration,
        rrd=rrd.resolve(),
        rate_hz=rate,
        hello_rate_hz=args.hello_rate,
        local_cache=not args.no_local_cache,
        cache_control=not args.no_cache_control,
        rmax_hz=rmax,
        mission=args.mission,
        world=args.world,
        reliability=args.reliability,
        history=args.history,
        depth=args.depth,
    )
    try:
        summary = run_demo(options, workdir)
    except DemoError as exc:
        print(f"arpz demo: error: FAILED: {exc}", file=sys.stderr)
        return 1
    # with --json on stdout, stdout is the JSON alone and the words go to stderr
    words = sys.stderr if args.json == JSON_TO_STDOUT else sys.stdout
    print(format_summary(summary), file=words)
    print(f"Rerun recording: {options.rrd}  (open it with: rerun {options.rrd})", file=words)
    result = (summary.get("mission") or {}).get("result")
    if mission:
        if result is None:
            return fail("demo", "FAILED: the mission never started (were all robots present?)", 1)
        print(
            f"mission {result['mission'].upper()}: {result['reason']} "
            f"(time {result['duration_s']:.1f} s, path error "
            f"{_fmt(result['path_error_m'])} m mean, {_fmt(result['path_error_max_m'])} m max)",
            file=words,
        )
    emit_json({**result, "summary": summary} if mission and result else summary, args.json)
    if mission and result and result["mission"] != "success":
        return MISSION_FAILED
    return 0
