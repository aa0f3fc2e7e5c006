"""The fleet load test's pure part: from the CEDDPs' summaries, the workers' own counts and the
process samples to per-robot rows, per-CEDDP and fleet figures, the knee of a scaling curve, and
the CSV/PNG/text that show them.

No processes and no I/O besides writing the files asked for: the unit tests feed it dicts.

Definitions (docs/performance.md repeats them):

- ``offered`` = robots x topics x rate x the measured window: what the fleet was asked to send.
- ``sent``, ``delivered``, ``lost``: the CEDDP summary's per-robot ``sent`` (the robot's own final
  report), ``received`` and ``lost``; reconciled when ``sent == delivered + lost`` for every robot.
- fleet latency p50 = the median of the robots' p50; fleet latency p99 = the WORST robot's p99
  (an upper bound of the fleet's p99: a bound every robot meets); the same for staleness.
- the knee = the smallest N whose fleet p99 exceeds the latency bound (10 ms by default, the
  issue's target) or whose delivered/offered falls below 0.99; a point whose robots could not
  even send 99 % of the offered rate is flagged ``generator_limited``: there the load generator,
  not the CEDDP, was the limit.
- a run in which the hypervisor took at least ``STEAL_FLAG_CORES`` of the host's CPU is flagged
  ``steal_flagged``: the vCPU's pauses, which no process of the run can shorten, are in its
  latency max, and in its p99 when they are frequent (stop 42, fourteen 50-robot runs: 0.015-0.065
  cores stolen went with a worst-robot p99 of 13-82 ms, <= 0.002 with 5.6-8.4 ms, 0.005-0.010
  with 7.5-12.0 ms; a second with 0.1-0.2 cores stolen, with a max of 83-217 ms).
"""

from __future__ import annotations

import csv
import statistics
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

#: the knee's defaults: the issue's latency target and the delivered share below which a fleet
#: is not keeping up
P99_BOUND_MS = 10.0
MIN_DELIVERED_RATIO = 0.99
#: stolen CPU (cores, over the window) from which a run's tail is partly the hypervisor's: 1 %
#: of a core is 0.6 s of a 60 s run, 10 ms of pauses a second on average
STEAL_FLAG_CORES = 0.01

#: what the CEDDP does not publish (yet): reported as unavailable, with the reason
MISSING = {
    "ingest_backlog": (
        "this CEDDP published no CeddpStats.ingest_backlog_ms (its raw path, an older arpz, "
        "or samples without a router timestamp); the sensor path's busy share "
        "(ingest_load_max) stands in"
    ),
    "dashboard_dropped": (
        "this CEDDP published no CeddpStats.dashboard_dropped (arpz before the overload "
        "governor), and its summary.json's dashboard.dropped was a constant 0"
    ),
}


def unavailable(ceddps: Sequence[CeddpFigures]) -> dict[str, str]:
    """The figures this run could not report, each with what is missing."""
    out = {}
    if any(c.ingest_backlog_ms_max is None for c in ceddps):
        out["ingest_backlog"] = MISSING["ingest_backlog"]
    if any(c.dashboard_dropped is None for c in ceddps):
        out["dashboard_dropped"] = MISSING["dashboard_dropped"]
    return out


@dataclass(frozen=True)
class RobotRow:
    """One robot as its CEDDP saw it, checked against the robot's own count."""

    robot: str
    ceddp: int
    worker: int
    sent: int
    delivered: int
    lost: int
    #: sent according to the worker process (the agent's counters at shutdown)
    worker_sent: int | None
    #: scheduler ticks the robot's sensors fell behind (its worker's CPU was short)
    late_ticks: int
    final_report: bool
    latency_ms_p50: float | None
    latency_ms_p99: float | None
    staleness_ms_p99: float | None
    #: the largest latency of any of its samples (None from a CEDDP that does not report it)
    latency_ms_max: float | None = None
    #: its latencies were measured on the CEDDP's clock (its clock offset taken out), and the
    #: offset used (ms; None: none measured)
    clock_corrected: bool = False
    clock_offset_ms: float | None = None

    @property
    def reconciled(self) -> bool:
        return self.final_report and self.sent == self.delivered + self.lost


@dataclass(frozen=True)
class ProcessFigures:
    """CPU (fraction of one core over the measured window, and its busiest second) and memory of
    one process, from /proc."""

    pid: int
    cpu_cores: float
    cpu_cores_peak: float
    rss_mb: float
    rss_peak_mb: float


@dataclass(frozen=True)
class CeddpFigures:
    index: int
    partition: str
    robots: int
    process: ProcessFigures | None
    sent: int
    delivered: int
    lost: int
    delivered_per_s: float
    latency_ms_p50: float | None
    latency_ms_p99: float | None
    staleness_ms_p99: float | None
    #: samples the sensor reader's full worker queue refused (reliable readers NACK them again)
    ingest_queue_dropped: int | None
    #: CPU per delivered sample, microseconds (cpu_cores x window / delivered)
    cpu_us_per_sample: float | None = None
    #: from its CeddpStats reports (None where it does not publish them): the highest busy
    #: share of its sensor path, dashboard frames dropped, its measured capacity (samples/s)
    ingest_load_max: float | None = None
    dashboard_dropped: int | None = None
    capacity_hz: float | None = None
    #: the longest a sample waited in the CEDDP before its sensor path took it, ms: its
    #: ingest backlog in time (the highest CeddpStats interval of the window; else the
    #: summary's since start)
    ingest_backlog_ms_max: float | None = None
    #: the 99th percentile of that wait over the run's pulls that found samples waiting (the
    #: summary's): far below the robots' p99 latency, the latency was spent before the router
    #: took the sample in (the robots, the link, the router's receive threads)
    ingest_backlog_ms_p99: float | None = None
    #: each sample's time inside the CEDDP, from the router's receipt to the end of the sensor
    #: path's pass that processed it, p99 and max over the run (upper bounds; the summary's
    #: ingest.sojourn_ms_*): the CEDDP's own share of the robots' latency
    sojourn_ms_p99: float | None = None
    sojourn_ms_max: float | None = None
    latency_ms_max: float | None = None
    #: the sensor reader's NACKs and the samples it received twice (a resend of what had come):
    #: on a link that loses nothing, every NACK asked for what was only queued
    ingest_nacks: int | None = None
    ingest_duplicates: int | None = None


@dataclass(frozen=True)
class FleetPoint:
    """One run of the load test: the fleet's figures (one point of a scaling curve)."""

    robots: int
    topics: int
    rate_hz: float
    processes: int
    ceddps: int
    window_s: float
    offered: int
    sent: int
    delivered: int
    lost: int
    offered_per_s: float
    delivered_per_s: float
    sent_ratio: float
    delivered_ratio: float
    latency_ms_p50: float | None
    latency_ms_p99: float | None
    staleness_ms_p99: float | None
    ceddp_cpu_cores: float | None
    ceddp_rss_mb: float | None
    #: the CEDDPs' and the robot workers' CPU per delivered sample, microseconds
    ceddp_cpu_us_per_sample: float | None
    workers_cpu_us_per_sample: float | None
    workers_cpu_cores: float
    host_busy_cores: float | None
    reconciled: bool
    generator_limited: bool
    failures: list[str] = field(default_factory=list)
    latency_ms_max: float | None = None
    #: every robot's latency was corrected by its clock offset, and the largest |offset| (ms)
    clock_corrected: bool = False
    clock_offset_ms_max: float | None = None
    #: the median robot's p99: beside the worst robot's, whether the fleet's tail is every
    #: robot's or a few robots' (at 50 robots one robot's 77 ms against a median of 13)
    latency_ms_p99_median_robot: float | None = None
    #: CPU the hypervisor gave to other guests during the window, in cores (within host busy)
    host_steal_cores: float | None = None
    #: how the kernel scheduled the workers' robots threads ("SCHED_BATCH, nice 10"), as they
    #: read it themselves; several, "; "-separated, if the workers differed
    workers_scheduling: str | None = None
    #: the most the hypervisor took in one second of the window, in cores
    host_steal_cores_peak: float | None = None

    @property
    def steal_flagged(self) -> bool:
        """The hypervisor took enough CPU that the latency tail is (partly) its pauses."""
        return self.host_steal_cores is not None and self.host_steal_cores >= STEAL_FLAG_CORES


def _num(row: Mapping[str, Any], key: str) -> float | None:
    value = row.get(key)
    return float(value) if isinstance(value, int | float) else None


def robot_rows(
    placement: Mapping[str, tuple[int, int]],
    summaries: Sequence[Mapping[str, Any]],
    worker_counts: Mapping[str, Mapping[str, Any]],
) -> list[RobotRow]:
    """One row per robot of ``placement`` (robot -> (CEDDP index, worker index)), read from the
    summary of the CEDDP whose partition it belongs to (every summary lists every robot's
    reports, only that one ingests its samples). A robot its CEDDP never saw gets zeros and no
    final report, so it fails reconciliation loudly instead of vanishing."""
    rows = []
    for robot, (ceddp, worker) in sorted(placement.items()):
        summary = summaries[ceddp] if ceddp < len(summaries) else {}
        row: Mapping[str, Any] = (summary.get("robots") or {}).get(robot) or {}
        own = worker_counts.get(robot) or {}
        rows.append(
            RobotRow(
                robot=robot,
                ceddp=ceddp,
                worker=worker,
                sent=int(row.get("sent", 0)),
                delivered=int(row.get("received", 0)),
                lost=int(row.get("lost", 0)),
                worker_sent=int(own["sent"]) if "sent" in own else None,
                late_ticks=int(own.get("late_ticks", 0)),
                final_report=bool(row.get("final_stats", False)),
                latency_ms_p50=_num(row, "latency_ms_p50"),
                latency_ms_p99=_num(row, "latency_ms_p99"),
                staleness_ms_p99=_num(row, "staleness_ms_p99"),
                latency_ms_max=_num(row, "latency_ms_max"),
                clock_corrected=bool(row.get("clock_corrected", False)),
                clock_offset_ms=_num(row.get("clock") or {}, "offset_ms"),
            )
        )
    return rows


def failures_of(rows: Iterable[RobotRow]) -> list[str]:
    """Every reconciliation failure, one sentence each."""
    problems = []
    for r in rows:
        if not r.final_report:
            problems.append(f"{r.robot}: its final report did not reach CEDDP {r.ceddp}")
        if r.sent != r.delivered + r.lost:
            problems.append(
                f"{r.robot}: sent {r.sent} != delivered {r.delivered} + lost {r.lost} "
                f"({r.sent - r.delivered - r.lost:+d} unaccounted)"
            )
        if r.worker_sent is not None and r.final_report and r.worker_sent != r.sent:
            problems.append(
                f"{r.robot}: the agent counted {r.worker_sent} sent, its final report {r.sent}"
            )
    return problems


def _median(values: Iterable[float | None]) -> float | None:
    present = [v for v in values if v is not None]
    return statistics.median(present) if present else None


def _worst(values: Iterable[float | None]) -> float | None:
    present = [v for v in values if v is not None]
    return max(present) if present else None


def _count(value: object) -> int | None:
    return value if isinstance(value, int) else None


def ceddp_figures(
    index: int,
    summary: Mapping[str, Any],
    rows: Sequence[RobotRow],
    process: ProcessFigures | None,
    window_s: float,
    self_report: Mapping[str, Any] | None = None,
) -> CeddpFigures:
    """``self_report``: what the CEDDP said of itself (``load_max``, ``dashboard_dropped``,
    ``capacity_hz``; absent keys or None: not published)."""
    mine = [r for r in rows if r.ceddp == index]
    channel = (summary.get("ingest") or {}).get("channel") or {}
    dropped = _count(channel.get("queue_dropped"))
    delivered = sum(r.delivered for r in mine)
    own = self_report or {}
    # the worst interval the CEDDP reported in the window; else its summary's since start
    backlog = _num(own, "backlog_ms_max")
    if backlog is None:
        backlog = _num(summary.get("ingest") or {}, "backlog_ms_max")
    return CeddpFigures(
        index=index,
        partition=str(summary.get("partition", "?")),
        robots=len(mine),
        process=process,
        sent=sum(r.sent for r in mine),
        delivered=delivered,
        lost=sum(r.lost for r in mine),
        delivered_per_s=delivered / window_s if window_s > 0 else 0.0,
        latency_ms_p50=_median(r.latency_ms_p50 for r in mine),
        latency_ms_p99=_worst(r.latency_ms_p99 for r in mine),
        staleness_ms_p99=_worst(r.staleness_ms_p99 for r in mine),
        ingest_queue_dropped=dropped,
        ingest_nacks=_count(channel.get("nacks")),
        ingest_duplicates=_count(channel.get("duplicates")),
        cpu_us_per_sample=per_sample_us(
            process.cpu_cores if process else None, window_s, delivered
        ),
        latency_ms_max=_worst(r.latency_ms_max for r in mine),
        ingest_load_max=own.get("load_max"),
        dashboard_dropped=own.get("dashboard_dropped"),
        capacity_hz=own.get("capacity_hz"),
        ingest_backlog_ms_max=backlog,
        ingest_backlog_ms_p99=_num(summary.get("ingest") or {}, "backlog_ms_p99"),
        sojourn_ms_p99=_num(summary.get("ingest") or {}, "sojourn_ms_p99"),
        sojourn_ms_max=_num(summary.get("ingest") or {}, "sojourn_ms_max"),
    )


def per_sample_us(cores: float | None, window_s: float, samples: int) -> float | None:
    """CPU microseconds per sample: cores x window / samples (None without samples or CPU)."""
    if cores is None or samples <= 0:
        return None
    return round(cores * window_s / samples * 1e6, 1)


def fleet_point(
    *,
    rows: Sequence[RobotRow],
    ceddps: Sequence[CeddpFigures],
    topics: int,
    rate_hz: float,
    processes: int,
    window_s: float,
    workers_cpu_cores: float,
    host_busy_cores: float | None,
    failures: Sequence[str] = (),
    host_steal_cores: float | None = None,
    workers_scheduling: str | None = None,
    host_steal_cores_peak: float | None = None,
) -> FleetPoint:
    """The fleet's figures; ``failures``: problems found outside the rows (a process that did
    not stop, ...), added to the reconciliation failures."""
    offered_per_s = len(rows) * topics * rate_hz
    offered = round(offered_per_s * window_s)
    sent = sum(r.sent for r in rows)
    delivered = sum(r.delivered for r in rows)
    problems = [*failures, *failures_of(rows)]
    cpus = [c.process.cpu_cores for c in ceddps if c.process is not None]
    rss = [c.process.rss_peak_mb for c in ceddps if c.process is not None]
    sent_ratio = sent / offered if offered else 0.0
    return FleetPoint(
        robots=len(rows),
        topics=topics,
        rate_hz=rate_hz,
        processes=processes,
        ceddps=len(ceddps),
        window_s=round(window_s, 3),
        offered=offered,
        sent=sent,
        delivered=delivered,
        lost=sum(r.lost for r in rows),
        offered_per_s=offered_per_s,
        delivered_per_s=delivered / window_s if window_s > 0 else 0.0,
        sent_ratio=sent_ratio,
        delivered_ratio=delivered / offered if offered else 0.0,
        latency_ms_p50=_median(r.latency_ms_p50 for r in rows),
        latency_ms_p99=_worst(r.latency_ms_p99 for r in rows),
        latency_ms_p99_median_robot=_median(r.latency_ms_p99 for r in rows),
        staleness_ms_p99=_worst(r.staleness_ms_p99 for r in rows),
        latency_ms_max=_worst(r.latency_ms_max for r in rows),
        clock_corrected=bool(rows) and all(r.clock_corrected for r in rows),
        clock_offset_ms_max=_worst(
            abs(r.clock_offset_ms) for r in rows if r.clock_offset_ms is not None
        ),
        ceddp_cpu_cores=sum(cpus) if cpus else None,
        ceddp_rss_mb=sum(rss) if rss else None,
        ceddp_cpu_us_per_sample=per_sample_us(sum(cpus) if cpus else None, window_s, delivered),
        workers_cpu_us_per_sample=per_sample_us(workers_cpu_cores, window_s, delivered),
        workers_cpu_cores=workers_cpu_cores,
        host_busy_cores=host_busy_cores,
        host_steal_cores=host_steal_cores,
        host_steal_cores_peak=host_steal_cores_peak,
        workers_scheduling=workers_scheduling,
        reconciled=not problems,
        generator_limited=sent_ratio < MIN_DELIVERED_RATIO,
        failures=problems,
    )


# ------------------------------------------------------------------------------------ the knee
@dataclass(frozen=True)
class Knee:
    robots: int
    reason: str


def over_the_knee(
    p99_ms: float | None,
    delivered_ratio: float,
    *,
    p99_bound_ms: float = P99_BOUND_MS,
    min_ratio: float = MIN_DELIVERED_RATIO,
) -> str | None:
    """Why a point is past the knee ("" never: None when it is not)."""
    if p99_ms is None:
        return "nothing delivered"
    if p99_ms > p99_bound_ms:
        return f"p99 {p99_ms:.1f} ms > {p99_bound_ms:g} ms"
    if delivered_ratio < min_ratio:
        return f"delivered/offered {delivered_ratio:.3f} < {min_ratio:g}"
    return None


def find_knee(
    points: Iterable[tuple[int, float | None, float]],
    *,
    p99_bound_ms: float = P99_BOUND_MS,
    min_ratio: float = MIN_DELIVERED_RATIO,
) -> Knee | None:
    """The first N (in ascending order) of ``(N, p99 ms, delivered/offered)`` past the knee;
    None if every point is within bounds."""
    for robots, p99, ratio in sorted(points, key=lambda p: p[0]):
        reason = over_the_knee(p99, ratio, p99_bound_ms=p99_bound_ms, min_ratio=min_ratio)
        if reason is not None:
            return Knee(robots, reason)
    return None


def fleet_knee(points: Sequence[FleetPoint], **bounds: float) -> Knee | None:
    return find_knee(((p.robots, p.latency_ms_p99, p.delivered_ratio) for p in points), **bounds)


def ceddp_knees(
    points: Sequence[FleetPoint], per_ceddp: Sequence[Sequence[CeddpFigures]], **bounds: float
) -> dict[int, Knee | None]:
    """The knee of each CEDDP over a sweep, by the fleet size N, from its own robots' figures
    (its offered load is its share of the fleet's)."""
    knees: dict[int, Knee | None] = {}
    indexes = sorted({c.index for figures in per_ceddp for c in figures})
    for index in indexes:
        series = []
        for point, figures in zip(points, per_ceddp, strict=True):
            mine = next((c for c in figures if c.index == index), None)
            if mine is None or not mine.robots:
                continue
            offered = mine.robots * point.topics * point.rate_hz * point.window_s
            ratio = mine.delivered / offered if offered else 0.0
            series.append((point.robots, mine.latency_ms_p99, ratio))
        knees[index] = find_knee(series, **bounds)
    return knees


# --------------------------------------------------------------------------------- the outputs
def result_dict(
    point: FleetPoint, ceddps: Sequence[CeddpFigures], rows: Sequence[RobotRow]
) -> dict[str, Any]:
    """The JSON document of one run."""
    return {
        "fleet": {**asdict(point), "steal_flagged": point.steal_flagged},
        "ceddps": [asdict(c) for c in ceddps],
        "robots": [{**asdict(r), "reconciled": r.reconciled} for r in rows],
        "unavailable": unavailable(ceddps),
    }


ROBOT_COLUMNS = [f.name for f in fields(RobotRow)] + ["reconciled"]


def write_robot_csv(path: Path, rows: Sequence[RobotRow]) -> None:
    with path.open("w", newline="", encoding="utf-8") as fh:
        out = csv.writer(fh)
        out.writerow(ROBOT_COLUMNS)
        for r in rows:
            out.writerow([*(getattr(r, name) for name in ROBOT_COLUMNS[:-1]), r.reconciled])


SWEEP_COLUMNS = [f.name for f in fields(FleetPoint) if f.name != "failures"] + ["steal_flagged"]


def write_sweep_csv(
    path: Path, points: Sequence[FleetPoint], per_ceddp: Sequence[Sequence[CeddpFigures]]
) -> None:
    """One line per fleet size, the fleet's columns then each CEDDP's CPU, delivered and p99."""
    count = max((len(figures) for figures in per_ceddp), default=0)
    extra = []
    for index in range(count):
        extra += [f"ceddp{index}_cpu_cores", f"ceddp{index}_delivered_per_s"]
        extra += [f"ceddp{index}_latency_ms_p99"]
    with path.open("w", newline="", encoding="utf-8") as fh:
        out = csv.writer(fh)
        out.writerow([*SWEEP_COLUMNS, *extra])
        for point, figures in zip(points, per_ceddp, strict=True):
            cells: list[Any] = [getattr(point, name) for name in SWEEP_COLUMNS]
            for c in figures:
                cells += [c.process.cpu_cores if c.process else None, c.delivered_per_s]
                cells += [c.latency_ms_p99]
            out.writerow(cells)


def _fmt(value: float | None, spec: str = ".2f") -> str:
    """``n/a`` for a figure that was not measured or not published."""
    return "n/a" if value is None else format(value, spec)


def format_run(point: FleetPoint, ceddps: Sequence[CeddpFigures], rows: Sequence[RobotRow]) -> str:
    """What the command prints after a run: the robots (at most 20 lines, worst first), each
    CEDDP, the fleet, and the reconciliation verdict."""
    lines = [
        f"{'robot':>10} {'ceddp':>5} {'sent':>8} {'delivered':>9} {'lost':>6} "
        f"{'p50 ms':>7} {'p99 ms':>7} {'stale p99':>9} {'late':>6}  reconciled"
    ]
    worst = sorted(rows, key=lambda r: (r.reconciled, -(r.latency_ms_p99 or 0.0)))
    for r in worst[:20]:
        lines.append(
            f"{r.robot:>10} {r.ceddp:>5} {r.sent:>8} {r.delivered:>9} {r.lost:>6} "
            f"{_fmt(r.latency_ms_p50):>7} {_fmt(r.latency_ms_p99):>7} "
            f"{_fmt(r.staleness_ms_p99):>9} {r.late_ticks:>6}  {'yes' if r.reconciled else 'NO'}"
        )
    if len(rows) > 20:
        lines.append(f"... {len(rows) - 20} more robots (all in the JSON/CSV)")
    for c in ceddps:
        proc = c.process
        cpu = f"{proc.cpu_cores:.2f} cores (peak {proc.cpu_cores_peak:.2f})" if proc else "n/a"
        rss = f"{proc.rss_peak_mb:.0f} MB" if proc else "n/a"
        lines.append(
            f"CEDDP {c.index} ({c.partition}, {c.robots} robots): delivered "
            f"{c.delivered_per_s:,.0f}/s, lost {c.lost}, p50 {_fmt(c.latency_ms_p50)} ms, "
            f"p99 {_fmt(c.latency_ms_p99)} ms, max {_fmt(c.latency_ms_max)} ms, CPU {cpu}, "
            f"RSS {rss}, ingest queue dropped "
            f"{_fmt(c.ingest_queue_dropped, 'd')}, NACKs {_fmt(c.ingest_nacks, 'd')}, "
            f"duplicates {_fmt(c.ingest_duplicates, 'd')}, sensor path busy (max) "
            f"{_fmt(c.ingest_load_max)}, ingest backlog (max) "
            f"{_fmt(c.ingest_backlog_ms_max)} ms (p99 {_fmt(c.ingest_backlog_ms_p99)} ms), "
            f"time in the CEDDP p99 {_fmt(c.sojourn_ms_p99)} ms (max {_fmt(c.sojourn_ms_max)} "
            "ms), dashboard frames dropped "
            f"{_fmt(c.dashboard_dropped, 'd')}, CPU per sample "
            f"{_fmt(c.cpu_us_per_sample, '.0f')} us"
        )
    p = point
    lines.append(
        f"fleet: {p.robots} robots x {p.topics} topics x {p.rate_hz:g} Hz in {p.processes} "
        f"processes, {p.window_s:.1f} s: offered {p.offered_per_s:,.0f}/s, sent "
        f"{p.sent_ratio:.3f} of it, delivered {p.delivered_per_s:,.0f}/s "
        f"({p.delivered_ratio:.3f} of offered), lost {p.lost}, latency p50 "
        f"{_fmt(p.latency_ms_p50)} ms, p99 (worst robot) {_fmt(p.latency_ms_p99)} ms "
        f"(median robot {_fmt(p.latency_ms_p99_median_robot)} ms), "
        f"max {_fmt(p.latency_ms_max)} ms, staleness p99 {_fmt(p.staleness_ms_p99)} ms, "
        + (
            f"clock corrected (largest |offset| {_fmt(p.clock_offset_ms_max)} ms)"
            if p.clock_corrected
            else "NOT clock corrected (some robot reported no clock offset)"
        )
    )
    lines.append(
        f"CPU: CEDDP {_fmt(p.ceddp_cpu_cores)} cores "
        f"({_fmt(p.ceddp_cpu_us_per_sample, '.0f')} us a sample), robot workers "
        f"{p.workers_cpu_cores:.2f} cores"
        + (f" ({p.workers_scheduling})" if p.workers_scheduling else "")
        + f", host busy {_fmt(p.host_busy_cores)} of "
        f"{_host_cores()} cores (stolen by the hypervisor {_fmt(p.host_steal_cores)}"
        + (
            f", up to {_fmt(p.host_steal_cores_peak)} in one second)"
            if p.host_steal_cores_peak is not None
            else ")"
        )
        + ("; GENERATOR-LIMITED: the robots sent < 99 % of the offered rate" * p.generator_limited)
    )
    if p.steal_flagged:
        lines.append(
            f"STOLEN: the hypervisor took {_fmt(p.host_steal_cores)} cores "
            f"({(p.host_steal_cores or 0) * p.window_s:.1f} s of CPU over the window; up to "
            f"{_fmt(p.host_steal_cores_peak)} cores in one second): this run's latency "
            "includes the vCPU's pauses (its max, and its p99 when they are frequent); "
            "compare runs without them"
        )
    missing = unavailable(ceddps)
    if missing:
        lines.append("unavailable: " + "; ".join(f"{k}: {v}" for k, v in missing.items()))
    if p.reconciled:
        lines.append(f"reconciled: sent == delivered + lost for all {p.robots} robots")
    else:
        lines.append(f"FAILED: {len(p.failures)} problem(s):")
        lines += [f"  {problem}" for problem in p.failures[:30]]
    return "\n".join(lines)


def _host_cores() -> int:
    import os

    return os.cpu_count() or 1


def _cpu_of(figures: Sequence[CeddpFigures], index: int) -> float | None:
    process = figures[index].process if len(figures) > index else None
    return process.cpu_cores if process is not None else None


def _ring(ax: Any, points: Sequence[FleetPoint], values: list[Any], style: str, label: str) -> None:
    """Open markers around the flagged points of a curve (nothing when none is flagged)."""
    if points:
        ax.plot(
            [p.robots for p in points], values, style, fillstyle="none", markersize=10, label=label
        )


def plot_sweep(
    path: Path,
    points: Sequence[FleetPoint],
    per_ceddp: Sequence[Sequence[CeddpFigures]],
    *,
    p99_bound_ms: float = P99_BOUND_MS,
    title: str = "",
) -> None:
    """Three panels against the fleet size N: p99 latency (with the bound), CPU of each CEDDP
    (with one core), delivered vs offered samples/s; the knee as a vertical line on each."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    knee = fleet_knee(points, p99_bound_ms=p99_bound_ms)
    ns = [p.robots for p in points]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    lat, cpu, rate = axes
    lat.plot(ns, [p.latency_ms_p99 for p in points], "o-", label="p99 (worst robot)")
    lat.plot(ns, [p.latency_ms_p50 for p in points], "s--", label="p50 (median robot)")
    stolen = [p for p in points if p.steal_flagged]
    _ring(lat, stolen, [p.latency_ms_p99 for p in stolen], "mD", "hypervisor stole >= 0.01 core")
    lat.axhline(p99_bound_ms, color="grey", linestyle=":", label=f"bound {p99_bound_ms:g} ms")
    lat.set_yscale("log")
    lat.set_ylabel("latency robot -> CEDDP ingest (ms)")
    count = max((len(f) for f in per_ceddp), default=0)
    for index in range(count):
        values = [_cpu_of(f, index) for f in per_ceddp]
        cpu.plot(ns, values, "o-", label=f"CEDDP {index}")
    cpu.plot(ns, [p.workers_cpu_cores for p in points], "x--", label="robot workers")
    cpu.axhline(1.0, color="grey", linestyle=":", label="one core")
    cpu.set_ylabel("CPU (cores)")
    rate.plot(ns, [p.offered_per_s for p in points], "k:", label="offered")
    rate.plot(ns, [p.sent / p.window_s if p.window_s else 0 for p in points], "x--", label="sent")
    rate.plot(ns, [p.delivered_per_s for p in points], "o-", label="delivered")
    limited = [p for p in points if p.generator_limited]
    _ring(rate, limited, [p.delivered_per_s for p in limited], "rs", "generator-limited")
    rate.set_ylabel("samples/s")
    for ax in axes:
        ax.set_xlabel("robots")
        ax.set_xscale("log")
        ax.grid(True, alpha=0.3)
        if knee is not None:
            ax.axvline(knee.robots, color="red", alpha=0.6, label=f"knee: N={knee.robots}")
        ax.legend(fontsize=8)
    p = points[0] if points else None
    heading = title or (
        f"{p.topics} topics x {p.rate_hz:g} Hz per robot, {p.ceddps} CEDDP(s)" if p else ""
    )
    if knee is not None:
        heading += f"; knee at N={knee.robots} ({knee.reason})"
    fig.suptitle(heading)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
