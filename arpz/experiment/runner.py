"""Run an experiment's cells: emulated links, a real fleet per cell, one results.csv row each.

Per cell: one ``arpz.netem`` proxy per robot in front of the CEDDP's UDP endpoint (clean while
the sessions open and the readers match, impaired from the moment every robot runs), then
``arpz.tools.launch.run_fleet`` with the cell's configs, then the row. A ``lab:PROFILE``
network runs the cell in the kernel lab instead (``arpz.lab``: CEDDP and robots in their own network
namespaces, the profile applied by nftables and tbf to each robot's real link, over
``lab_link``), for what a user-space UDP proxy cannot impair: TCP, TLS and QUIC links, dead
zones longer than the lease, roaming. Cells already in results.csv
are skipped, so an interrupted run resumes where it stopped; Ctrl-C (or SIGTERM) ends the cell
in progress without writing it, and ``run_fleet`` ends its processes.
"""

from __future__ import annotations

import shutil
import signal
import socket
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import Any, TextIO

import msgspec

from arpz.core.errors import ArpzError
from arpz.experiment.fleet import cell_fleet, configured_qos
from arpz.experiment.results import append_row, done_keys, error_row, row_from_summary
from arpz.experiment.spec import (
    Cell,
    ExperimentSpec,
    NetworkProfile,
    lab_profile_name,
    normalise_config,
)
from arpz.netem import GilbertElliott, Impairments, NetemProxy
from arpz.tools.launch import LaunchError, Proc, free_port, on_fresh_ports, run_fleet

#: seconds a cell takes beyond its measurement (starting and stopping 4 processes), for the ETA
#: before the first cell has been timed
START_STOP_S = 8.0
#: after the mission's verdict is due, how long to wait for it before stopping the fleet
MISSION_MARGIN_S = 30.0


def impairments(profile: NetworkProfile) -> Impairments:
    burst = GilbertElliott(p=profile.burst_p, r=profile.burst_r) if profile.burst_p > 0 else None
    return Impairments(
        loss=profile.loss_pct / 100.0,
        burst=burst,
        delay_s=profile.delay_ms / 1000.0,
        jitter_s=profile.jitter_ms / 1000.0,
        rate_bps=profile.rate_kbps * 1000.0,
    )


@dataclass
class Links:
    """The robots' emulated links: clean until ``impair()``, so Zenoh sessions open and the
    reliable channel matches before the first loss (a lost handshake fails ``zenoh.open``)."""

    proxies: dict[str, NetemProxy]
    profiles: dict[str, NetworkProfile]
    impaired_at: float | None = None
    #: the last time the fleet was seen running (the end of the measured window)
    last_seen: float | None = None
    #: the proxies' totals when the links were impaired and when they were made clean again:
    #: the link loss is reported over that window only, not diluted by the clean setup and
    #: shutdown (the final reports and acknowledgements would otherwise halve it in a short cell)
    at_impair: dict[str, int] | None = None
    at_clear: dict[str, int] | None = None

    @classmethod
    def start(cls, forward: str, profiles: dict[str, NetworkProfile], seed: int) -> Links:
        proxies: dict[str, NetemProxy] = {}
        try:
            for index, robot in enumerate(profiles):
                proxies[robot] = NetemProxy(
                    "udp/127.0.0.1:0", forward, Impairments(), seed=seed * 10 + index
                ).start()
        except BaseException:
            for proxy in proxies.values():
                proxy.stop()
            raise
        return cls(proxies, profiles)

    def endpoint(self, robot: str) -> str:
        return f"udp/127.0.0.1:{self.proxies[robot].listen_port}"

    def totals(self) -> dict[str, int]:
        totals = {"received": 0, "dropped": 0}
        for proxy in self.proxies.values():
            report = proxy.report()
            for counters in (report.up, report.down):
                totals["received"] += counters.received
                totals["dropped"] += counters.dropped
        return totals

    def impair(self) -> None:
        self.at_impair = self.totals()
        for robot, proxy in self.proxies.items():
            proxy.set_impairments(impairments(self.profiles[robot]))
        self.impaired_at = time.monotonic()

    def clear(self) -> None:
        """Back to a clean link for the shutdown: the robots' final reports (plain puts) and
        the channel's last acknowledgements must not be lost, or the counts cannot reconcile."""
        for proxy in self.proxies.values():
            proxy.set_impairments(Impairments())
        self.at_clear = self.totals()

    def stop(self) -> dict[str, int]:
        """Stop the proxies; the datagrams received and dropped during the impaired window
        (the whole run when it never started or never ended)."""
        for proxy in self.proxies.values():
            proxy.stop()
        start = self.at_impair or {"received": 0, "dropped": 0}
        end = self.at_clear or self.totals()
        return {key: end[key] - start[key] for key in ("received", "dropped")}


class Interrupted(ArpzError):
    """Ctrl-C or SIGTERM: the cell in progress is not written."""


def _run_on_fresh_ports(
    spec: ExperimentSpec, cell: Cell, workdir: Path, rrd: Path
) -> tuple[dict[str, Any], Links, dict[str, int]]:
    """Start the links and the fleet on ports free a moment ago and run the cell's window;
    (the CEDDP's summary, the links, their totals over the impaired window). Raises
    LaunchError (PortTaken when another process took a port meanwhile); the links are stopped
    whatever happens."""
    udp_port, tcp_port = free_port(socket.SOCK_DGRAM), free_port()
    forward = f"udp/127.0.0.1:{udp_port}"
    profiles = {robot: spec.profile(spec.robot_network(cell, robot)) for robot in spec.robot_names}
    links = Links.start(forward, profiles, spec.seed + cell.repeat)
    try:
        fleet = cell_fleet(
            spec,
            cell,
            listen=[forward, f"tcp/127.0.0.1:{tcp_port}"],
            robot_connect={r: links.endpoint(r) for r in spec.robot_names},
            rrd=str(rrd),
        )

        def until(ceddp: Proc) -> bool:
            # called first once every robot runs: the measured window starts there, and ends
            # after duration_s (or at the mission's verdict) with the links made clean again
            now = time.monotonic()
            if links.impaired_at is None:
                links.impair()
            started_at = links.impaired_at or now
            links.last_seen = now
            if spec.mission is not None:
                over = ceddp.has_line("arpz.ceddp: mission ")
            else:
                over = now - started_at >= spec.duration_s
            if over:
                links.clear()
            return over

        # a backstop only: until() ends the window (a mission ends with its verdict, the time
        # limit being the judge's)
        backstop = (
            spec.mission.time_limit_s + MISSION_MARGIN_S
            if spec.mission is not None
            else spec.duration_s + MISSION_MARGIN_S
        )
        summary = run_fleet(
            fleet, workdir, duration_s=backstop, until=until, progress=None, label=cell.slug
        )
    finally:
        link_totals = links.stop()
    return summary, links, link_totals


def _run_in_lab(
    spec: ExperimentSpec, cell: Cell, workdir: Path, rrd: Path
) -> tuple[dict[str, Any], dict[str, int], float, dict[str, float]]:
    """The cell in a kernel lab of its own: (the CEDDP's summary, the links' frames seen and
    dropped over the run, the seconds measured, each process's CPU seconds over the window).
    Raises LaunchError when the lab cannot run it
    (no root or nft: the reason says what is missing)."""
    # imported here: arpz.lab brings pyroute2 and needs root, which proxy cells do not
    from arpz.experiment.link_bytes import uplink_bytes
    from arpz.lab import Lab, LabError, Timeline, parse_profile
    from arpz.lab.fleet import PORT, run_fleet_in_lab, secure
    from arpz.lab.timeline import TIMELINE_FILE

    names = {robot: lab_profile_name(spec.robot_network(cell, robot)) for robot in spec.robot_names}
    proxy_nets = [robot for robot, name in names.items() if name is None]
    if proxy_nets:
        raise LaunchError(
            f"{cell.slug}: a lab cell's robots all need lab profiles; {', '.join(proxy_nets)} "
            "have proxy ones (robot_networks)"
        )
    profiles = {robot: parse_profile(name or "") for robot, name in names.items()}
    workdir.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    try:
        with (
            open(workdir / "lab.log", "w", encoding="utf-8") as progress,
            Lab.create(spec.robot_names, timeline=Timeline(workdir / TIMELINE_FILE)) as lab,
        ):
            endpoint = f"{spec.lab_link}/{lab.ceddp_address}:{PORT}"
            fleet = cell_fleet(
                spec,
                cell,
                listen=[endpoint],
                robot_connect=dict.fromkeys(spec.robot_names, endpoint),
                rrd=str(rrd),
            )
            secure(fleet, spec.lab_link, lab, workdir)
            duration = (
                spec.mission.time_limit_s + MISSION_MARGIN_S / 3
                if spec.mission is not None
                else spec.duration_s
            )
            result = run_fleet_in_lab(
                lab,
                fleet,
                workdir,
                profiles=profiles,
                duration_s=duration,
                seed=spec.seed + cell.repeat,
                progress=progress,
            )
            bytes_up = uplink_bytes(lab)
    except LabError as exc:
        raise LaunchError(f"{cell.slug}: the lab: {exc}") from exc
    counters = result.counters.values()
    seen = sum(c.up_seen + c.down_seen for c in counters)
    dropped = sum(c.up_dropped + c.down_dropped for c in counters)
    link = {"received": seen, "dropped": dropped, "bytes_up": bytes_up}
    return result.summary, link, time.monotonic() - started, result.cpu_s


def run_cell(
    spec: ExperimentSpec, cell: Cell, out: Path, *, keep_logs: bool = False
) -> dict[str, Any]:
    """Run one cell and return its results.csv row (status "error" when a part failed)."""
    started = time.monotonic()
    workdir = out / "runs" / cell.slug
    if workdir.exists():
        shutil.rmtree(workdir)
    rrd_dir = out / "rrd"
    rrd_dir.mkdir(parents=True, exist_ok=True)
    rrd = rrd_dir / f"{cell.slug}.rrd"
    if cell.middleware == "ros2":
        return _run_ros2(spec, cell, workdir, started, keep_logs=keep_logs)
    cpu_s: dict[str, float] = {}
    try:
        if lab_profile_name(cell.network) is not None:
            summary, link_totals, measured, cpu_s = _run_in_lab(spec, cell, workdir, rrd)
        else:
            summary, links, link_totals = on_fresh_ports(
                lambda: _run_on_fresh_ports(spec, cell, workdir, rrd),
                lambda why: print(f"{cell.slug}: {why}", file=sys.stderr),
            )
            measured = (links.last_seen or started) - (links.impaired_at or started)
    except LaunchError as exc:
        return error_row(
            cell, experiment=spec.name, error=str(exc), wall_s=time.monotonic() - started
        )
    row = row_from_summary(
        cell,
        summary,
        experiment=spec.name,
        link=link_totals,
        measured_s=measured,
        wall_s=time.monotonic() - started,
        rrd=str(rrd.relative_to(out)),
        configured=configured_qos(spec, cell),
        cpu_s=cpu_s,
    )
    if not keep_logs:
        # keep the summary (small) and drop the logs and configs of a successful cell
        kept = ("summary.json", "ceddp.toml", "robot1.toml", "lab_timeline.jsonl")
        _prune(workdir, lambda path: path.name in kept)
    return row


def _prune(workdir: Path, keep: Callable[[Path], bool]) -> None:
    """Remove what a successful cell's directory holds but ``keep``s."""
    for path in workdir.iterdir():
        if keep(path):
            continue
        if path.is_dir():
            shutil.rmtree(path)
        else:
            path.unlink()


def _run_ros2(
    spec: ExperimentSpec, cell: Cell, workdir: Path, started: float, *, keep_logs: bool
) -> dict[str, Any]:
    """A ROS 2 cell (arpz.experiment.ros2): its row, or an error row naming what failed."""
    from arpz.experiment.ros2.machines_cell import run_ros2_cell
    from arpz.experiment.ros2.machines_row import CountersError, ros2_row

    try:
        row = ros2_row(cell, run_ros2_cell(spec, cell, workdir), experiment=spec.name)
    except (LaunchError, CountersError) as exc:
        return error_row(
            cell, experiment=spec.name, error=str(exc), wall_s=time.monotonic() - started
        )
    if not keep_logs:
        # keep the nodes' counters and the timeline, drop the logs
        _prune(workdir, lambda path: path.suffix == ".json" or path.name == "lab_timeline.jsonl")
    return row


def middleware_plan(spec: ExperimentSpec) -> list[str]:
    """Which configurations run on which middleware, and the ones a middleware skips (LC and
    CC are arpz features: a grid naming them has no ROS 2 cells for them)."""
    runs = spec.middleware_configs()
    every = [normalise_config(c) for c in spec.configs]
    lines = []
    for middleware, configs in runs.items():
        skipped = [c for c in every if c not in configs]
        line = f"  {middleware}: {', '.join(configs)}"
        if skipped:
            line += f" (not {', '.join(skipped)}: arpz features)"
        lines.append(line)
    return ["configurations per middleware:", *lines]


def _duration(seconds: float) -> str:
    seconds = max(0, int(seconds))
    if seconds >= 3600:
        return f"{seconds // 3600}h{seconds % 3600 // 60:02d}m"
    return f"{seconds // 60}m{seconds % 60:02d}s"


def run_experiment(
    spec: ExperimentSpec,
    out: Path,
    *,
    progress: TextIO = sys.stderr,
    keep_logs: bool = False,
    on_row: Callable[[dict[str, Any]], None] | None = None,
) -> int:
    """Run every cell not yet in ``out/results.csv``; returns how many cells were run.

    Raises Interrupted (after writing every finished cell) on Ctrl-C or SIGTERM."""
    # absolute: each process runs in its own cell directory, so a relative ``--out`` (as the
    # docs write it) would name config files that do not exist from there
    out = out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    (out / "spec.json").write_bytes(msgspec.json.format(msgspec.json.encode(spec)))
    results = out / "results.csv"
    done = done_keys(results)
    cells = spec.cells()
    todo = [c for c in cells if c.key not in done]
    print(
        f"{spec.name}: {len(cells)} cells, {len(cells) - len(todo)} already done, "
        f"{len(todo)} to run; results in {results}",
        file=progress,
        flush=True,
    )
    if spec.middlewares != ["arpz"]:
        for line in middleware_plan(spec):
            print(line, file=progress, flush=True)
    per_cell = (
        spec.mission.time_limit_s * 0.7 if spec.mission is not None else spec.duration_s
    ) + START_STOP_S
    timings: list[float] = []
    previous = signal.getsignal(signal.SIGTERM)
    # started in the background by a shell, SIGINT may be ignored: Ctrl-C must still work
    signal.signal(signal.SIGINT, signal.default_int_handler)

    def on_term(signum: int, frame: FrameType | None) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_term)
    begun = time.monotonic()
    try:
        for index, cell in enumerate(todo, start=1):
            mean = sum(timings) / len(timings) if timings else per_cell
            eta = mean * (len(todo) - index + 1)
            print(
                f"[{index}/{len(todo)}] {cell.label} (ETA {_duration(eta)})",
                file=progress,
                flush=True,
            )
            try:
                row = run_cell(spec, cell, out, keep_logs=keep_logs)
            except KeyboardInterrupt:
                raise Interrupted(
                    f"interrupted during {cell.label}: {index - 1} cells written this run; "
                    f"rerun the same command to continue"
                ) from None
            append_row(results, row)
            timings.append(float(row["wall_s"]))
            print(f"    {_row_line(row)}", file=progress, flush=True)
            if on_row is not None:
                on_row(row)
    finally:
        signal.signal(signal.SIGTERM, previous)
    print(
        f"{spec.name}: {len(todo)} cells in {_duration(time.monotonic() - begun)}",
        file=progress,
        flush=True,
    )
    return len(todo)


def _fmt(value: Any, unit: str = "") -> str:
    if value is None or value == "":
        return "-"
    if isinstance(value, float):
        return f"{value:.3g}{unit}"
    return f"{value}{unit}"


def _row_line(row: dict[str, Any]) -> str:
    if row["status"] != "ok":
        return f"ERROR after {row['wall_s']:.0f} s: {row['error'][:300]}"
    text = (
        f"ok in {row['wall_s']:.0f} s: Hello {row['hello_received']}/{row['hello_sent']} "
        f"rtt p50 {_fmt(row['latency_ms_p50'], ' ms')}; samples sent {row['samples_sent']} "
        f"held {row['samples_held_back']} lost {row['samples_lost']} "
        f"({_fmt(row['sample_loss_pct'], ' %')}), p50 {_fmt(row['sample_latency_ms_p50'], ' ms')}; "
        f"R {_fmt(row['rate_hz'])} Hz D {row['qos_depth']}; staleness p99 "
        f"{_fmt(row.get('staleness_ms_p99'), ' ms')}; link loss {_fmt(row['link_loss_pct'], ' %')}"
    )
    if row.get("cpu_s_ceddp") is not None:
        text += (
            f"; CPU ceddp {_fmt(row['cpu_s_ceddp'], ' s')} robots "
            f"{_fmt(row.get('cpu_s_robots'), ' s')}"
        )
    if row.get("downlink_reconciled") == "no":
        text += f"; downlink NOT reconciled: {row['downlink_unreconciled']}"
    if row.get("mission"):
        text += f"; mission {row['mission']}: {row['mission_reason']}"
    return text
