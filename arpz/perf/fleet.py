"""``python -m arpz.perf fleet``: a fleet load generator that measures the CEDDP.

N real robot agents (``RobotAgent``: local cache, channel writers, reports, each with its own
Zenoh client session) packed into P worker processes (``arpz.perf.fleet_worker``), against K real
CEDDP processes (``python -m arpz.ceddp``: ingest, cache control, planner, dashboard), started
and stopped by pid with ``arpz.tools.launch``. Packing robots into a few processes is what lets
50-200 robots run on a 2-core machine; the CEDDP's own CPU and memory are read from /proc, so its
cost
is measured apart from the robots'.

With K > 1 the CEDDPs form one Zenoh router mesh (each connects to the first) with key-space
partitions (docs/operations.md): robot ``c{k}-r{i}`` belongs to partition ``c{k}-$*`` and
connects to CEDDP k. docs/performance.md has the results and the definitions of every figure
(see also ``arpz.perf.fleet_report``).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, TextIO

import tomli_w

from arpz.core.config import CeddpConfig, RobotConfig, from_dict
from arpz.core.errors import ArpzError
from arpz.core.protocol.qos import MAX_HEARTBEAT_BACKOFF
from arpz.perf.fleet_report import (
    P99_BOUND_MS,
    CeddpFigures,
    FleetPoint,
    ProcessFigures,
    ceddp_figures,
    ceddp_knees,
    fleet_knee,
    fleet_point,
    format_run,
    plot_sweep,
    result_dict,
    robot_rows,
    write_robot_csv,
    write_sweep_csv,
)
from arpz.perf.fleet_watch import CeddpWatcher
from arpz.runtime.startup import add_json_option, emit_json, fail, stop_on_signals
from arpz.tools.launch import LaunchError, Proc, free_port

#: the kinds of seed 001 Table 1, cycled over a robot's topics (a mixed, realistic fleet)
TOPIC_KINDS = ("lidar", "imu", "ultrasonic", "dht11", "flame", "pir", "light")
FLEET = "perf"


#: how a worker process runs its robots' periodic jobs (``--robot-threads``)
ROBOT_THREADS = ("shared", "own")
#: when each robot's periodic jobs start after the go (``--robot-phases``)
ROBOT_PHASES = ("spread", "aligned")
#: the worker processes' Linux scheduling policy (``--robot-sched``)
ROBOT_SCHED = ("normal", "batch")


class FleetArgumentError(ArpzError, ValueError):
    """A fleet option that cannot work; the message says which and why (exit code 2)."""


@dataclass(frozen=True)
class FleetOptions:
    robots: int = 10
    topics: int = 8
    rate_hz: float = 100.0
    processes: int = 2
    duration_s: float = 10.0
    ceddps: int = 1
    local_cache: bool = False
    history: str = "keep_all"
    depth: int = 10
    zenoh_config: str | None = None
    p99_bound_ms: float = P99_BOUND_MS
    #: the sensor profile's heartbeat period (None: the profile's default, 100 ms)
    heartbeat_ms: float | None = None
    #: the worker processes' niceness: the CEDDP gets the CPU first, the robots what is left
    robot_nice: int = 10
    #: "batch": the workers run under SCHED_BATCH, whose threads' wake-ups do not preempt a
    #: running thread (each robot's channel and Zenoh threads wait for the robots thread's
    #: time slice instead of taking the CPU from it); "normal": SCHED_OTHER
    robot_sched: str = "batch"
    #: a tick's sensor messages as one Zenoh message (the robots' default; False: one per topic)
    bundles: bool = True
    #: with bundles (and so piggybacked heartbeats): the longest a calm stream's heartbeat
    #: period grows, in periods (``QosProfile.heartbeat_backoff``; 1 = fixed)
    heartbeat_backoff: int = 8
    #: "shared": one thread of each worker runs all its robots' periodic jobs; "own": a
    #: thread per robot, as ``RobotAgent.run`` (see ``arpz.perf.fleet_worker``)
    robot_threads: str = "shared"
    #: "spread": robot i of N runs each periodic job first i/N of the job's period after the
    #: go, so the fleet's ticks, reports, probes and clock exchanges are spread over their
    #: periods as independent robots' are; "aligned": all at the go (in lockstep within a
    #: worker process, and every report of the fleet in the same instant every second)
    robot_phases: str = "spread"


def check_options(o: FleetOptions) -> None:
    """Refuse what cannot run, before any process starts."""
    if o.robots < 1:
        raise FleetArgumentError(f"--robots must be >= 1, got {o.robots}")
    if o.topics < 1 or o.topics > 64:
        raise FleetArgumentError(f"--topics must be 1..64 (the CEDDP's limit), got {o.topics}")
    if not 0 < o.rate_hz <= 10_000:
        raise FleetArgumentError(f"--rate must be in (0, 10000] Hz, got {o.rate_hz:g}")
    if o.processes < 1:
        raise FleetArgumentError(f"--processes must be >= 1, got {o.processes}")
    if o.duration_s <= 0:
        raise FleetArgumentError(f"--duration must be > 0 s, got {o.duration_s:g}")
    if o.ceddps < 1 or o.ceddps > 8:
        raise FleetArgumentError(f"--ceddps must be 1..8, got {o.ceddps}")
    if o.ceddps > o.robots:
        raise FleetArgumentError(
            f"--ceddps {o.ceddps} > --robots {o.robots}: a CEDDP would serve nobody"
        )
    if o.robot_threads not in ROBOT_THREADS:
        raise FleetArgumentError(
            f"--robot-threads must be one of {', '.join(ROBOT_THREADS)}, got {o.robot_threads!r}"
        )
    if o.robot_phases not in ROBOT_PHASES:
        raise FleetArgumentError(
            f"--robot-phases must be one of {', '.join(ROBOT_PHASES)}, got {o.robot_phases!r}"
        )
    if o.robot_sched not in ROBOT_SCHED:
        raise FleetArgumentError(
            f"--robot-sched must be one of {', '.join(ROBOT_SCHED)}, got {o.robot_sched!r}"
        )
    if not 0 <= o.robot_nice <= 19:
        raise FleetArgumentError(f"--robot-nice must be 0..19, got {o.robot_nice}")
    if o.heartbeat_ms is not None and o.heartbeat_ms <= 0:
        raise FleetArgumentError(f"--heartbeat-ms must be > 0, got {o.heartbeat_ms:g}")
    if not 1 <= o.heartbeat_backoff <= MAX_HEARTBEAT_BACKOFF:
        raise FleetArgumentError(
            f"--heartbeat-backoff must be 1..{MAX_HEARTBEAT_BACKOFF}, got {o.heartbeat_backoff}"
        )
    if o.depth < 1:
        raise FleetArgumentError(f"--depth must be >= 1, got {o.depth}")
    if o.zenoh_config is not None and not Path(o.zenoh_config).is_file():
        raise FleetArgumentError(f"--zenoh-config {o.zenoh_config}: no such file")


def parse_sweep(text: str) -> list[int]:
    """``1,5,10,25`` -> [1, 5, 10, 25]: ascending, distinct, each >= 1."""
    try:
        sizes = [int(part) for part in text.split(",") if part.strip()]
    except ValueError:
        raise FleetArgumentError(
            f"--sweep wants robot counts like 1,5,10,25, got {text!r}"
        ) from None
    if not sizes or any(n < 1 for n in sizes) or sizes != sorted(set(sizes)):
        raise FleetArgumentError(
            f"--sweep wants ascending distinct robot counts >= 1, got {text!r}"
        )
    return sizes


# ---------------------------------------------------------------------------------- the plan
def robot_name(ceddp: int, index: int) -> str:
    return f"c{ceddp}-r{index:03d}"


def placement(o: FleetOptions) -> dict[str, tuple[int, int]]:
    """Robot -> (CEDDP, worker process): round robin over both, so every CEDDP and every worker
    gets the same share (within one)."""
    out: dict[str, tuple[int, int]] = {}
    for i in range(o.robots):
        ceddp = i % o.ceddps
        out[robot_name(ceddp, i // o.ceddps + 1)] = (ceddp, i % min(o.processes, o.robots))
    return out


def sensor_qos(o: FleetOptions) -> dict[str, Any]:
    qos: dict[str, Any] = {"reliability": "reliable", "history": o.history}
    if o.history == "keep_last":
        qos["depth"] = o.depth
    if o.heartbeat_ms is not None:
        qos["heartbeat_period_s"] = o.heartbeat_ms / 1000
    if o.bundles:  # the measured configuration of issue 17: bundles and piggybacked heartbeats
        qos["piggyback_heartbeats"] = True
        qos["heartbeat_backoff"] = o.heartbeat_backoff
    return qos


def ceddp_configs(o: FleetOptions, endpoints: list[str], workdir: Path) -> list[dict[str, Any]]:
    confs = []
    for k, endpoint in enumerate(endpoints):
        conf: dict[str, Any] = {
            "fleet": FLEET,
            "listen": [endpoint],
            "partition": "*" if o.ceddps == 1 else f"c{k}-$*",
            "rrd": str(workdir / f"ceddp{k}.rrd"),
            "summary_json": str(workdir / f"ceddp{k}.json"),
            "sensor_qos": sensor_qos(o),
        }
        if k > 0:
            conf["connect"] = [endpoints[0]]
        if o.zenoh_config:
            conf["zenoh_config"] = str(Path(o.zenoh_config).resolve())
        from_dict(conf, CeddpConfig, source=f"ceddp {k}")  # a config the CEDDP will refuse: now
        confs.append(conf)
    return confs


def robot_config(o: FleetOptions, robot: str, endpoint: str, seed: int) -> dict[str, Any]:
    conf: dict[str, Any] = {
        "robot_id": robot,
        "fleet": FLEET,
        "connect": [endpoint],
        "seed": seed,
        "sensors": [
            {"name": f"t{j:02d}", "kind": TOPIC_KINDS[j % len(TOPIC_KINDS)], "rate_hz": o.rate_hz}
            for j in range(o.topics)
        ],
        "local_cache": {"enabled": o.local_cache},
        "sensor_qos": sensor_qos(o),
        "bundle_sensors": o.bundles,
    }
    if o.zenoh_config:
        conf["zenoh_config"] = str(Path(o.zenoh_config).resolve())
    from_dict(conf, RobotConfig, source=robot)
    return conf


def worker_plan(
    o: FleetOptions, endpoints: list[str], workdir: Path
) -> tuple[dict[str, Any], dict[str, tuple[int, int]]]:
    where = placement(o)
    workers: list[list[dict[str, Any]]] = [[] for _ in range(min(o.processes, o.robots))]
    for seed, (robot, (ceddp, worker)) in enumerate(where.items(), start=1):
        workers[worker].append(robot_config(o, robot, endpoints[ceddp], seed))
    plan = {
        "workers": workers,
        "go_file": str(workdir / "go"),
        "nice": o.robot_nice,
        "sched": o.robot_sched,
        "robot_threads": o.robot_threads,
        "phases": robot_phases(o, list(where)),
        "zenoh_config": str(Path(o.zenoh_config).resolve()) if o.zenoh_config else None,
    }
    return plan, where


def robot_phases(o: FleetOptions, robots: list[str]) -> dict[str, float]:
    """Robot -> the fraction of each of its jobs' periods after the go at which the job first
    runs (``RobotAgent.stagger_jobs``): i/N (``--robot-phases spread``), or all 0. Robots
    packed into one process and released by one go file otherwise tick in lockstep and report
    together every second: the CEDDP gets bursts that independent robots would not send."""
    if o.robot_phases == "aligned":
        return {robot: 0.0 for robot in robots}
    return {robot: i / len(robots) for i, robot in enumerate(robots)}


# ------------------------------------------------------------------------------ /proc sampling
CLOCK_TICKS = os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid: int) -> float | None:
    """User + system CPU of a process (all threads), from /proc/PID/stat; None once it is gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text.rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLOCK_TICKS  # utime, stime (fields 14, 15)


def rss_mb(pid: int) -> tuple[float, float] | None:
    """(VmRSS, VmHWM) in MB from /proc/PID/status: the resident memory now and its peak."""
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    values = {}
    for line in text.splitlines():
        name, _, rest = line.partition(":")
        if name in ("VmRSS", "VmHWM"):
            values[name] = int(rest.split()[0]) / 1024
    if len(values) < 2:
        return None
    return values["VmRSS"], values["VmHWM"]


def host_busy_s() -> tuple[float, float, float]:
    """(busy, total, stolen) CPU seconds of the whole host since boot, from /proc/stat.

    Stolen time is CPU the hypervisor gave to other guests while this one had work. On this
    project's shared VM it stayed 0.00 cores in stop 38's slow windows (there the same work cost
    more CPU), but in stop 42's the 50-robot runs with 0.015-0.065 cores stolen had a worst-robot
    p99 of 13-82 ms and those with <= 0.002 one of 5.6-8.4 ms: the vCPU's pauses are the tail,
    so the report flags them (``FleetPoint.steal_flagged``)."""
    return host_cpu_seconds(Path("/proc/stat").read_text().splitlines()[0])


def host_cpu_seconds(cpu_line: str) -> tuple[float, float, float]:
    """``host_busy_s`` of the ``cpu`` line of /proc/stat (user nice system idle iowait irq
    softirq steal ..., in clock ticks)."""
    ticks = [int(v) for v in cpu_line.split()[1:]]
    idle = ticks[3] + (ticks[4] if len(ticks) > 4 else 0)
    steal = ticks[7] if len(ticks) > 7 else 0
    return (sum(ticks) - idle) / CLOCK_TICKS, sum(ticks) / CLOCK_TICKS, steal / CLOCK_TICKS


class ProcSampler:
    """CPU and RSS of some processes over the measured window, sampled every call of ``sample``
    (the busiest one-second interval is the peak)."""

    def __init__(self, pids: list[int]) -> None:
        self.pids = pids
        self.t0 = time.monotonic()
        self.cpu0 = {pid: cpu_seconds(pid) or 0.0 for pid in pids}
        self.host0 = host_busy_s()
        self.last = {pid: (self.t0, self.cpu0[pid]) for pid in pids}
        self.peak = dict.fromkeys(pids, 0.0)
        self.cpu_now = dict(self.cpu0)
        self.rss = dict.fromkeys(pids, (0.0, 0.0))
        self.t_end = self.t0
        self.host_end = self.host0
        self.host_last = (self.t0, self.host0)
        self.steal_peak = 0.0

    def sample(self) -> None:
        now = time.monotonic()
        for pid in self.pids:
            cpu = cpu_seconds(pid)
            if cpu is None:
                continue
            self.cpu_now[pid] = cpu
            t_last, cpu_last = self.last[pid]
            if now - t_last >= 1.0:
                self.peak[pid] = max(self.peak[pid], (cpu - cpu_last) / (now - t_last))
                self.last[pid] = (now, cpu)
            memory = rss_mb(pid)
            if memory is not None:
                self.rss[pid] = (memory[0], max(memory[1], self.rss[pid][1]))
        self.t_end = now
        self.host_end = host_busy_s()
        t_last, host_last = self.host_last
        if now - t_last >= 1.0:
            stolen = (self.host_end[2] - host_last[2]) / (now - t_last)
            self.steal_peak = max(self.steal_peak, stolen)
            self.host_last = (now, self.host_end)

    def cores(self, pid: int) -> float:
        span = self.t_end - self.t0
        return (self.cpu_now[pid] - self.cpu0[pid]) / span if span > 0 else 0.0

    def figures(self, pid: int) -> ProcessFigures:
        cores = self.cores(pid)
        return ProcessFigures(
            pid=pid,
            cpu_cores=round(cores, 3),
            cpu_cores_peak=round(max(self.peak[pid], cores), 3),
            rss_mb=round(self.rss[pid][0], 1),
            rss_peak_mb=round(self.rss[pid][1], 1),
        )

    def host_busy_cores(self) -> float | None:
        return self._host_cores(0)

    def host_steal_cores(self) -> float | None:
        """Cores' worth of CPU the hypervisor took from this host over the window."""
        return self._host_cores(2)

    def host_steal_cores_peak(self) -> float | None:
        """The most the hypervisor took in any one-second interval: whether the steal came as
        pauses (a burst) or spread thin over the window."""
        whole = self.host_steal_cores()
        return None if whole is None else round(max(self.steal_peak, whole), 3)

    def _host_cores(self, column: int) -> float | None:
        seconds = self.host_end[column] - self.host0[column]
        span = self.t_end - self.t0
        return round(seconds / span, 3) if span > 0 else None


# --------------------------------------------------------------------------------- one run
@dataclass(frozen=True)
class RunResult:
    point: FleetPoint
    ceddps: list[CeddpFigures]
    rows: list[Any]
    #: every pid this run started (all gone when ``run_load`` returns)
    pids: list[int]

    def as_dict(self) -> dict[str, Any]:
        return {**result_dict(self.point, self.ceddps, self.rows), "pids": self.pids}


def _stop_all(procs: list[Proc], timeout_s: float) -> list[str]:
    """SIGINT to all at once (ONE each: a second SIGINT may find the default handler back, in
    a process already on its way out), then wait for each; what does not stop in time prints
    its threads' stacks (SIGUSR1) into its log, is killed and reported."""
    for proc in procs:
        if proc.popen.poll() is None:
            proc.popen.send_signal(signal.SIGINT)
    deadline = time.monotonic() + timeout_s
    failures = []
    for proc in procs:
        try:
            code = proc.popen.wait(timeout=max(deadline - time.monotonic(), 0.1))
        except subprocess.TimeoutExpired:
            proc.popen.send_signal(signal.SIGUSR1)
            time.sleep(0.5)
            proc.kill()
            failures.append(
                f"{proc.name} did not stop within {timeout_s:g} s of SIGINT and was killed; "
                f"see {proc.log_path}"
            )
            continue
        if code != 0:
            failures.append(f"{proc.name} exited with code {code}; see {proc.log_path}")
    return failures


def _check_alive(procs: list[Proc]) -> None:
    for proc in procs:
        if proc.popen.poll() is not None:
            raise LaunchError(
                f"{proc.name} exited early with code {proc.popen.returncode}; "
                f"see {proc.log_path}:\n{proc.tail()}"
            )


def _received_so_far(paths: list[Path]) -> int | None:
    """What the CEDDPs' periodic summaries say has arrived (every summary_period_s)."""
    total = 0
    for path in paths:
        try:
            summary = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None
        total += sum(int(r.get("received", 0)) for r in summary.get("robots", {}).values())
    return total


def run_load(
    o: FleetOptions,
    workdir: Path,
    progress: TextIO | None = sys.stderr,
    stop: threading.Event | None = None,
) -> RunResult:
    """Start the CEDDPs and the workers, run ``o.duration_s`` with every robot sending, stop
    everything (SIGINT: final reports, summaries), and reduce. Every process started is ended
    on every exit path."""
    check_options(o)
    workdir.mkdir(parents=True, exist_ok=True)
    endpoints = [f"tcp/127.0.0.1:{free_port()}" for _ in range(o.ceddps)]
    ceddp_confs = ceddp_configs(o, endpoints, workdir)
    plan, where = worker_plan(o, endpoints, workdir)
    plan_path = workdir / "plan.json"
    plan_path.write_text(json.dumps(plan, indent=1), encoding="utf-8")
    procs: list[Proc] = []
    watcher: CeddpWatcher | None = None

    def say(text: str) -> None:
        if progress is not None:
            print(text, file=progress, flush=True)

    try:
        ceddps: list[Proc] = []
        for k, conf in enumerate(ceddp_confs):
            path = workdir / f"ceddp{k}.toml"
            path.write_text(tomli_w.dumps(conf), encoding="utf-8")
            proc = Proc.spawn(f"ceddp{k}", ["-m", "arpz.ceddp", "--config", str(path)], workdir)
            procs.append(proc)
            ceddps.append(proc)
            proc.wait_line("ready on", timeout_s=60)
        watcher = CeddpWatcher(FLEET, endpoints[0], o.ceddps, o.zenoh_config)
        workers = []
        for w in range(len(plan["workers"])):
            proc = Proc.spawn(
                f"worker{w}",
                ["-m", "arpz.perf", "fleet-worker", "--plan", str(plan_path), "--worker", str(w)],
                workdir,
            )
            procs.append(proc)
            workers.append(proc)
        for proc in workers:
            # 100 agents start in about 2 minutes on 2 cores (each waits for its matches)
            proc.wait_line(": ready", timeout_s=60 + 2.0 * o.robots)
        sampler = ProcSampler([p.popen.pid for p in procs])
        Path(plan["go_file"]).touch()
        say(f"fleet: {o.robots} robots in {len(workers)} processes running; logs in {workdir}")
        start = time.monotonic()
        summaries = [Path(c["summary_json"]) for c in ceddp_confs]
        while (elapsed := time.monotonic() - start) < o.duration_s and not (stop and stop.is_set()):
            time.sleep(min(0.5, max(o.duration_s - elapsed, 0.0)))
            _check_alive(procs)
            sampler.sample()
            if progress is not None:
                cpu = sum(sampler.cores(p.popen.pid) for p in ceddps)
                arrived = _received_so_far(summaries)
                print(
                    f"\rfleet: {elapsed:5.1f}/{o.duration_s:g} s, CEDDP CPU {cpu:.2f} cores, "
                    f"host busy {sampler.host_busy_cores() or 0:.2f} cores (stolen "
                    f"{sampler.host_steal_cores() or 0:.2f}), received "
                    f"{'...' if arrived is None else f'{arrived:,}'}   ",
                    end="",
                    file=progress,
                    flush=True,
                )
        sampler.sample()
        window_s = time.monotonic() - start
        say(f"\rfleet: {window_s:.1f} s, stopping the robots")
        failures = _stop_all(workers, timeout_s=60 + 0.2 * o.robots)
        counts: dict[str, dict[str, Any]] = {}
        ran_s = []
        scheduling: set[str] = set()
        for proc in workers:
            result = _last_json(proc)
            if result is None:
                failures.append(f"{proc.name} printed no result; see {proc.log_path}")
                continue
            counts.update(result["robots"])
            failures += result["errors"]
            ran_s.append(float(result["ran_s"]))
            scheduling.add(str(result.get("scheduling", "unknown")))
        # the robots sent from the go file to SIGINT: that is the window of the offered load
        load_s = sum(ran_s) / len(ran_s) if ran_s else window_s
        self_reports = [vars(r) for r in watcher.snapshot()]
        failures += _stop_all(ceddps, timeout_s=60)
        docs = []
        for k, path in enumerate(summaries):
            try:
                docs.append(json.loads(path.read_text(encoding="utf-8")))
            except (OSError, ValueError) as exc:
                failures.append(f"CEDDP {k} left no summary ({path}): {exc}")
                docs.append({})
    finally:
        if watcher is not None:
            watcher.close()
        for proc in procs:
            proc.kill()
    rows = robot_rows(where, docs, counts)
    figures = [
        ceddp_figures(k, docs[k], rows, sampler.figures(p.popen.pid), load_s, self_reports[k])
        for k, p in enumerate(ceddps)
    ]
    point = fleet_point(
        rows=rows,
        ceddps=figures,
        topics=o.topics,
        rate_hz=o.rate_hz,
        processes=len(workers),
        window_s=load_s,
        workers_cpu_cores=round(sum(sampler.cores(p.popen.pid) for p in workers), 3),
        host_busy_cores=sampler.host_busy_cores(),
        host_steal_cores=sampler.host_steal_cores(),
        host_steal_cores_peak=sampler.host_steal_cores_peak(),
        failures=failures,
        workers_scheduling="; ".join(sorted(scheduling)) or None,
    )
    return RunResult(point, figures, rows, [p.popen.pid for p in procs])


def _last_json(proc: Proc) -> dict[str, Any] | None:
    for line in reversed(proc.lines):
        if line.startswith("{"):
            try:
                value: dict[str, Any] = json.loads(line)
            except ValueError:
                continue
            return value
    return None


# ------------------------------------------------------------------------------------ the CLI
def add_fleet_parser(sub: Any) -> None:
    f = sub.add_parser("fleet", help="N robot agents in P processes against real CEDDP(s)")
    f.add_argument("--robots", type=int, default=10, help="N robots (default 10)")
    f.add_argument("--topics", type=int, default=8, help="sensor topics per robot (8)")
    f.add_argument("--rate", type=float, default=100.0, help="Hz per topic (100)")
    f.add_argument(
        "--size",
        type=int,
        help="not supported: the real agent sends Table 1 typed values (about 60 B a sample)",
    )
    f.add_argument("--processes", type=int, default=2, help="worker processes (2)")
    f.add_argument("--duration", type=float, default=10.0, help="seconds of load (10)")
    f.add_argument("--ceddps", type=int, default=1, help="CEDDPs in one router mesh (1)")
    f.add_argument("--local-cache", action="store_true", help="robots' local cache on (off)")
    f.add_argument("--history", choices=["keep_all", "keep_last"], default="keep_all")
    f.add_argument("--depth", type=int, default=10, help="KEEP_LAST depth (10)")
    f.add_argument(
        "--robot-nice",
        type=int,
        default=10,
        help="niceness of the robot processes (10): the CEDDP is served first",
    )
    f.add_argument(
        "--robot-sched",
        choices=ROBOT_SCHED,
        default="batch",
        help="the robot processes' scheduling policy: batch (default; SCHED_BATCH: their "
        "threads' wake-ups do not preempt a running robot) or normal (SCHED_OTHER)",
    )
    f.add_argument(
        "--robot-threads",
        choices=ROBOT_THREADS,
        default="shared",
        help="shared (default): one thread of each worker process runs all its robots' "
        "sensing ticks; own: a thread per robot, whose GIL convoy halved what 50 robots sent",
    )
    f.add_argument(
        "--robot-phases",
        choices=ROBOT_PHASES,
        default="spread",
        help="spread (default): each robot's periodic jobs (ticks, reports, probes) start at "
        "its own phase of their periods, as independent robots' do; aligned: all at the go",
    )
    f.add_argument(
        "--heartbeat-ms", type=float, help="sensor writers' heartbeat period (default 100)"
    )
    f.add_argument(
        "--heartbeat-backoff",
        type=int,
        default=8,
        help="a calm stream's heartbeat period grows up to this many periods (8; 1 = fixed)",
    )
    f.add_argument(
        "--no-bundles",
        action="store_true",
        help="robots send one Zenoh message per topic, not one bundle per tick (the A/B)",
    )
    f.add_argument("--p99-bound-ms", type=float, default=P99_BOUND_MS, help="the knee's bound")
    f.add_argument("--sweep", help="robot counts, e.g. 1,5,10,25,50,100: the scaling curve")
    f.add_argument("--workdir", type=Path, help="configs, logs, summaries (default: a temp dir)")
    add_json_option(f, "the result")
    f.add_argument("--csv", type=Path, metavar="FILE", help="per robot; with --sweep per N")
    f.add_argument("--png", type=Path, metavar="FILE", help="the scaling curve (with --sweep)")
    w = sub.add_parser("fleet-worker", help=argparse.SUPPRESS)
    w.add_argument("--plan", type=Path, required=True)
    w.add_argument("--worker", type=int, required=True)


def options_from_args(args: argparse.Namespace) -> FleetOptions:
    if args.size is not None:
        raise FleetArgumentError(
            "--size: the robot agent sends the typed values of seed 001 Table 1 (floats, "
            "booleans, short strings: about 60 B a sample with its header), so a payload size "
            "cannot be chosen; large samples are measured by benchmarks/large_messages.py"
        )
    if args.png is not None and not args.sweep:
        raise FleetArgumentError("--png draws the scaling curve: give --sweep too")
    options = FleetOptions(
        robots=args.robots,
        topics=args.topics,
        rate_hz=args.rate,
        processes=args.processes,
        duration_s=args.duration,
        ceddps=args.ceddps,
        local_cache=args.local_cache,
        history=args.history,
        depth=args.depth,
        zenoh_config=args.zenoh_config,
        p99_bound_ms=args.p99_bound_ms,
        robot_nice=args.robot_nice,
        robot_sched=args.robot_sched,
        heartbeat_ms=args.heartbeat_ms,
        bundles=not args.no_bundles,
        heartbeat_backoff=args.heartbeat_backoff,
        robot_threads=args.robot_threads,
        robot_phases=args.robot_phases,
    )
    check_options(options)
    return options


def run_sweep(
    o: FleetOptions,
    sizes: list[int],
    workdir: Path,
    progress: TextIO | None = sys.stderr,
    stop: threading.Event | None = None,
) -> tuple[list[RunResult], dict[str, Any]]:
    """One run per fleet size (its own subfolder); the sweep's document with the knees."""
    results = []
    not_run: dict[str, str] = {}
    for n in sizes:
        if stop is not None and stop.is_set():
            break
        if progress is not None:
            print(f"--- sweep: {n} robots", file=progress, flush=True)
        options = replace(o, robots=n, processes=min(o.processes, n), ceddps=min(o.ceddps, n))
        try:
            result = run_load(options, workdir / f"n{n}", progress, stop)
        except LaunchError as exc:
            # a fleet that cannot even start is past any knee: keep the curve measured so far
            not_run[str(n)] = str(exc).splitlines()[0]
            if progress is not None:
                print(f"sweep: {n} robots FAILED to run: {exc}", file=progress, flush=True)
            break
        if progress is not None:
            print(format_run(result.point, result.ceddps, result.rows), file=progress, flush=True)
        results.append(result)
    points = [r.point for r in results]
    knee = fleet_knee(points, p99_bound_ms=o.p99_bound_ms)
    knees = ceddp_knees(points, [r.ceddps for r in results], p99_bound_ms=o.p99_bound_ms)
    doc = {
        "knee": None if knee is None else {"robots": knee.robots, "reason": knee.reason},
        "knee_definition": (
            f"the first N whose worst robot's p99 exceeds {o.p99_bound_ms:g} ms or whose "
            "delivered/offered is below 0.99"
        ),
        "ceddp_knees": {
            str(k): None if v is None else {"robots": v.robots, "reason": v.reason}
            for k, v in knees.items()
        },
        "points": [r.as_dict() for r in results],
        "not_run": not_run,
    }
    return results, doc


def main(args: argparse.Namespace) -> int:
    """``fleet``: exit 0 when everything reconciled, 1 when not (FAILED printed), 2 bad args."""
    if args.command == "fleet-worker":
        from arpz.perf.fleet_worker import run_worker

        print(json.dumps(run_worker(args.plan, args.worker, stop_on_signals())), flush=True)
        sys.stderr.flush()
        # every session is closed and the result printed: skip the interpreter's finalization,
        # where a Zenoh callback thread of one of the many closed sessions aborted the process
        # once ("FATAL: exception not rethrown", exit -6, 26 robots in 4 processes)
        os._exit(0)
    try:
        options = options_from_args(args)
        sizes = parse_sweep(args.sweep) if args.sweep else None
    except FleetArgumentError as exc:
        print(f"arpz.perf fleet: {exc}", file=sys.stderr)
        return 2
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="arpz-fleet-"))
    stop = stop_on_signals()  # SIGINT/SIGTERM: stop the load early, still stop cleanly
    try:
        if sizes is None:
            result = run_load(options, workdir, stop=stop)
            doc = result.as_dict()
            print(format_run(result.point, result.ceddps, result.rows), flush=True)
            if args.csv:
                write_robot_csv(args.csv, result.rows)
            ok = result.point.reconciled
        else:
            results, doc = run_sweep(options, sizes, workdir, stop=stop)
            points = [r.point for r in results]
            per_ceddp = [r.ceddps for r in results]
            if args.csv:
                write_sweep_csv(args.csv, points, per_ceddp)
            if args.png:
                plot_sweep(args.png, points, per_ceddp, p99_bound_ms=options.p99_bound_ms)
            print(f"knee: {doc['knee'] or 'none within the sweep'} ({doc['knee_definition']})")
            for k, knee in doc["ceddp_knees"].items():
                print(f"knee of CEDDP {k}: {knee or 'none within the sweep'}")
            for n, reason in doc["not_run"].items():
                print(f"FAILED: {n} robots could not run: {reason}")
            ok = all(p.reconciled for p in points) and not doc["not_run"]
            if not ok:
                print("FAILED: some runs did not reconcile (see above)")
    except LaunchError as exc:
        return fail("perf fleet", f"FAILED: {exc}", 1)
    emit_json(doc, args.json)
    return 0 if ok else 1
