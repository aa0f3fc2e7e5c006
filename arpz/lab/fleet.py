"""A CEDDP and N robots as real processes inside a kernel lab, each robot's link driven by its
profile: what ``python -m arpz lab run`` does.

The configs are the demo's (``arpz.tools.demo.demo_spec``: same fleet, presets, Hello relay, sensor
QoS) with the endpoint on the lab's server address; ``tls`` and ``quic`` add the fleet
certificates and Zenoh files of ``deploy/tls/make_fleet_certs.py`` (mutual TLS and access
control, as deployed). The timeline is written beside the CEDDP's summary.json.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, TextIO

import tomli_w

from arpz.lab.impair import ProfileRunner
from arpz.lab.names import LabError
from arpz.lab.net import Lab, LinkCounters
from arpz.lab.profiles import LinkState, Profile, parse_assignments
from arpz.lab.timeline import TIMELINE_FILE, Entry, Timeline, state_of
from arpz.tools.demo import DemoOptions, check_summary, demo_spec
from arpz.tools.launch import FleetSpec, LaunchError, Proc

#: the links a lab fleet can use (quic needs the same certificates as tls)
LINKS = ("tcp", "udp", "tls", "quic")
#: the CEDDP's port: its namespace is its own, so no other process can hold it
PORT = 7447
CERT_SCRIPT = Path(__file__).resolve().parents[2] / "deploy" / "tls" / "make_fleet_certs.py"
#: seconds between progress lines
PROGRESS_EVERY_S = 5.0


@dataclass(frozen=True)
class LabRunOptions:
    robots: int = 2
    link: str = "tcp"
    duration_s: float = 60.0
    #: ``--profile`` values: ``ROBOT=PROFILE`` or ``PROFILE`` (every robot not named)
    profiles: tuple[str, ...] = ()
    seed: int = 0
    #: the demo's settings (rate, reliability, QoS...); its ``robots`` is replaced by ours
    demo: DemoOptions = field(default_factory=DemoOptions)

    def __post_init__(self) -> None:
        if self.link not in LINKS:
            raise ValueError(f"link must be one of {', '.join(LINKS)}, got {self.link!r}")
        if self.robots < 1 or not self.duration_s > 0:
            raise ValueError("robots must be >= 1 and duration > 0")

    @property
    def robot_names(self) -> list[str]:
        return [f"robot{i}" for i in range(1, self.robots + 1)]


@dataclass
class LabRunResult:
    summary: dict[str, Any]
    #: the lab's timeline file (None: the timeline was kept in memory only)
    timeline: Path | None
    #: what ``arpz.tools.demo.check_summary`` finds (reconciliation, robots that never reported)
    problems: list[str]
    counters: dict[str, LinkCounters]
    #: CPU seconds (utime + stime) of each process (ceddp, robot1...) over the profile's window
    cpu_s: dict[str, float] = field(default_factory=dict)


def make_certs(out: Path, fleet: str, robots: list[str], server_ip: str) -> Path:
    """The fleet CA, certificates and Zenoh files for a CEDDP at ``server_ip``."""
    if not CERT_SCRIPT.exists():
        raise LabError(
            f"tls and quic need {CERT_SCRIPT.name} from an arpz checkout (deploy/tls/), "
            "which is not installed with the package"
        )
    args = [sys.executable, str(CERT_SCRIPT), "--out", str(out), "--fleet", fleet]
    done = subprocess.run(
        [*args, "--server-ip", server_ip, *robots],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    if done.returncode != 0:
        raise LabError(f"making the fleet's certificates failed: {done.stderr.strip()}")
    return out


def lab_spec(options: LabRunOptions, lab: Lab, workdir: Path) -> FleetSpec:
    """The demo's configs, on the lab's addresses and the chosen link."""
    endpoint = f"{options.link}/{lab.ceddp_address}:{PORT}"
    demo = replace(options.demo, robots=options.robots, rrd=workdir / "arpz-lab.rrd")
    spec = demo_spec(demo, endpoint)
    secure(spec, options.link, lab, workdir)
    return spec


def secure(spec: FleetSpec, link: str, lab: Lab, workdir: Path) -> None:
    """Over ``tls`` or ``quic``: the fleet's certificates and Zenoh files (mutual TLS, access
    control) made in ``workdir/tls`` and given to the CEDDP's and every robot's config."""
    if link not in ("tls", "quic"):
        return
    tls = make_certs(workdir / "tls", spec.ceddp["fleet"], list(spec.robots), lab.ceddp_address)
    spec.ceddp["zenoh_config"] = str(tls / "zenoh" / "ceddp-router.json5")
    for robot, conf in spec.robots.items():
        conf["zenoh_config"] = str(tls / "zenoh" / f"{robot}-client.json5")


def _write(path: Path, conf: dict[str, Any]) -> Path:
    path.write_text(tomli_w.dumps(conf), encoding="utf-8")
    return path


def describe(entry: Entry) -> str | None:
    """A progress line for a timeline event (None: not worth a line)."""
    robot = entry.get("robot", "")
    if entry["event"] == "profile":
        return f"lab: {robot} profile {entry['profile']}: {entry['description']}"
    if entry["event"] == "link":
        return (
            f"lab: t={entry['t']:6.1f} s {robot} {state_of(entry).describe()}, {entry['address']} "
            f"({entry['cause']})"
        )
    if entry["event"] == "error":
        return f"lab: t={entry['t']:6.1f} s {robot} ERROR {entry['message']}"
    return None


def run_lab(
    options: LabRunOptions,
    workdir: Path,
    *,
    progress: TextIO = sys.stderr,
    stop_requested: Callable[[], bool] = lambda: False,
) -> LabRunResult:
    """``python -m arpz lab run``: build the lab, run the demo's fleet in it with the
    profiles (``run_fleet_in_lab``), tear the lab down. LabError names what failed."""
    profiles = parse_assignments(list(options.profiles), options.robot_names)
    workdir.mkdir(parents=True, exist_ok=True)

    def say(entry: Entry) -> None:
        line = describe(entry)
        if line is not None:
            print(line, file=progress, flush=True)

    timeline = Timeline(workdir / TIMELINE_FILE, on_event=say)
    with Lab.create(options.robot_names, timeline=timeline) as lab:
        return run_fleet_in_lab(
            lab,
            lab_spec(options, lab, workdir),
            workdir,
            profiles=profiles,
            duration_s=options.duration_s,
            seed=options.seed,
            progress=progress,
            stop_requested=stop_requested,
        )


def run_fleet_in_lab(
    lab: Lab,
    spec: FleetSpec,
    workdir: Path,
    *,
    profiles: Mapping[str, Profile],
    duration_s: float,
    seed: int = 0,
    progress: TextIO = sys.stderr,
    stop_requested: Callable[[], bool] = lambda: False,
) -> LabRunResult:
    """Start ``spec``'s CEDDP and robots (named as the lab's robots, their endpoints on
    ``lab.ceddp_address``) in their namespaces, as ``arpz.tools.launch.run_fleet`` does on loopback;
    run the profiles for ``duration_s`` (or until ``stop_requested()``); clean the links so
    the final reports arrive; stop robots then CEDDP with SIGINT; return the summary. The
    caller owns the lab (and tears it down)."""
    ceddp_conf = dict(spec.ceddp, summary_json=str(workdir / "summary.json"))
    ceddp = lab.spawn(
        "ceddp",
        lab.ceddp_namespace,
        ["-m", "arpz.ceddp", "--config", str(_write(workdir / "ceddp.toml", ceddp_conf))],
        workdir,
    )
    ceddp.wait_line("ready on", timeout_s=60)
    robots: list[Proc] = []
    first = [r for r in spec.first if r in spec.robots]
    for group in (first, [r for r in spec.robots if r not in first]):
        started = [
            lab.spawn(
                robot,
                lab.robot(robot).namespace,
                ["-m", "arpz.robot", "--config", str(_write(workdir / f"{robot}.toml", conf))],
                workdir,
            )
            for robot, conf in ((r, spec.robots[r]) for r in group)
        ]
        robots += started
        for proc in started:
            proc.wait_line("running", timeout_s=60)
    print(
        f"lab {lab.lab_id}: CEDDP on {', '.join(spec.ceddp.get('listen', []))} and "
        f"{len(robots)} robots running; logs in {workdir}",
        file=progress,
        flush=True,
    )
    runner = ProfileRunner(lab, profiles, seed=seed, horizon_s=duration_s)
    failures: list[str] = []
    cpu0 = {proc.name: process_cpu_s(proc.popen.pid) for proc in (ceddp, *robots)}
    runner.start()
    try:
        _watch(lab, [ceddp, *robots], duration_s, progress, stop_requested)
    finally:
        try:
            runner.stop()
        except LabError as exc:
            failures.append(str(exc))
    for name, link in lab.robots.items():
        lab.apply(name, LinkState(subnet=link.state.subnet), "end of the run: clean links")
    counters = {name: lab.counters(name) for name in lab.robots}
    cpu = {p.name: process_cpu_s(p.popen.pid) - cpu0[p.name] for p in (ceddp, *robots)}
    for proc in reversed(robots):
        failures += _stop(proc, 20)
    failures += _stop(ceddp, 30)
    summary_path = workdir / "summary.json"
    if not summary_path.exists():
        failures.append(f"the CEDDP wrote no summary ({summary_path})")
    if failures:
        raise LabError("; ".join(failures))
    summary: dict[str, Any] = json.loads(summary_path.read_text(encoding="utf-8"))
    hello = bool(spec.robots.get("robot1", {}).get("hello", {}).get("enabled"))
    problems = check_summary(summary, len(spec.robots), hello=hello)
    return LabRunResult(summary, lab.timeline.path, problems, counters, cpu)


def _watch(
    lab: Lab,
    procs: list[Proc],
    duration_s: float,
    progress: TextIO,
    stop_requested: Callable[[], bool],
) -> None:
    """Wait out the run; a process that exits early is a LabError (unless a stop was asked
    for: a Ctrl-C at a terminal reaches the children too). Every ``PROGRESS_EVERY_S`` a line
    with what each link dropped since the last one."""
    start = last = time.monotonic()
    before = {name: lab.counters(name) for name in lab.robots}
    while (elapsed := time.monotonic() - start) < duration_s and not stop_requested():
        for proc in procs:
            if proc.popen.poll() is not None and not stop_requested():
                raise LabError(
                    f"{proc.name} exited early with code {proc.popen.returncode}; "
                    f"see {proc.log_path}:\n{proc.tail()}"
                )
        if time.monotonic() - last >= PROGRESS_EVERY_S:
            last = time.monotonic()
            now = {name: lab.counters(name) for name in lab.robots}
            links = ", ".join(_dropped(name, before[name], now[name]) for name in lab.robots)
            print(f"lab: {elapsed:5.1f}/{duration_s:g} s; {links}", file=progress, flush=True)
            before = now
        time.sleep(0.1)


def _dropped(robot: str, before: LinkCounters, now: LinkCounters) -> str:
    """What ``robot``'s link dropped between two readings, each way."""

    def share(dropped: int, seen: int) -> str:
        return f"{dropped}/{seen}" + (f" ({100 * dropped / seen:.0f} %)" if seen else "")

    up = share(now.up_dropped - before.up_dropped, now.up_seen - before.up_seen)
    down = share(now.down_dropped - before.down_dropped, now.down_seen - before.down_seen)
    return f"{robot} dropped up {up} down {down}"


def process_cpu_s(pid: int) -> float:
    """utime + stime of a running process, seconds (0 once it is gone): what it cost over a
    window is the difference of two readings, read before it stops (its shutdown not counted)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _stop(proc: Proc, timeout_s: float) -> list[str]:
    try:
        code = proc.stop(timeout_s)
    except LaunchError as exc:
        return [str(exc)]
    return [] if code == 0 else [f"{proc.name} exited with code {code}; see {proc.log_path}"]
