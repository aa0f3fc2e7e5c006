"""results.csv: one row per finished cell, appended and flushed at once.

A row is written whole or not at all (one ``write`` of a complete line, then flush and fsync), so
an interrupted run leaves a consistent file and a rerun can skip every cell already in it. The
columns are what seed 001 Figures 10, 11 and 16 plot, the counters that must reconcile, and the
QoS actually used (read back from the CEDDP, not from the spec).
"""

from __future__ import annotations

import csv
import io
import json
import os
import statistics
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import msgspec

from arpz.experiment.spec import Cell, ExperimentSpec, SpecError, format_rate

COLUMNS: tuple[str, ...] = (
    "experiment",
    "rmax_hz",
    "depth",
    "config",
    "repeat",
    "network",
    # "arpz" or "ros2" (rows of files written before it existed read as "arpz")
    "middleware",
    "status",
    # the Hello round trip robot1 -> CEDDP -> relay -> CEDDP -> robot1 (seed 001 Fig. 9-11)
    "latency_ms_p50",
    "latency_ms_p99",
    "loss_pct",
    "hello_sent",
    "hello_received",
    "hello_lost",
    # every sensor sample of every robot
    "sample_latency_ms_p50",
    "sample_latency_ms_p99",
    # sample latencies on the CEDDP's clock: every robot's clock offset taken out (true/false),
    # and the largest |offset| measured (ms)
    "clock_corrected",
    "clock_offset_ms_max",
    "sample_loss_pct",
    "samples_produced",
    "samples_sent",
    "samples_held_back",
    "samples_write_failures",
    "samples_received",
    "samples_lost",
    "samples_discarded",
    "samples_retransmitted",
    "samples_overwritten_unacked",
    # robots whose final counters reached the CEDDP (without them sent/lost are not final)
    "final_reports",
    # the QoS actually used (OPT: the CEDDP's last assignment; otherwise the fixed one)
    "rate_hz",
    # the rate per topic the publishers achieved over the window (ROS 2 cells: sent / window)
    "rate_hz_achieved",
    "qos_depth",
    "deadline_ms",
    "qos_epochs",
    "qos_applied",
    # how stale the CEDDP's view was: per change of value, how long it held another value than
    # the robot's latest reading (sensor topics of every robot)
    "staleness_ms_p50",
    "staleness_ms_p99",
    "staleness_ms_max",
    # the local cache forgot what it had sent after a loss (it resends the next reading)
    "cache_forgets",
    # CEDDP -> robot, through the reliable channel: the Hello hops (cmd/hello) and the other
    # commands (cmd/velocity ...), written by the CEDDP and accounted for by the robots
    "hello_hops_written",
    "hello_hops_delivered",
    "hello_hops_lost",
    "commands_written",
    "commands_delivered",
    "commands_lost",
    "commands_expired",
    "downlink_reconciled",
    "downlink_unreconciled",
    "watchdog_stops",
    # QoS mismatches between robots and CEDDP, and the samples refused because of them
    "incompatible_qos",
    "samples_refused",
    # the hallway mission (seed 001 Fig. 16); empty for the sensor fleet
    "mission",
    "mission_reason",
    "mission_duration_s",
    # what the emulated links did (both directions, all robots)
    "link_datagrams",
    "link_dropped",
    "link_loss_pct",
    # bytes the robots sent over their lab links (robot -> access point; lab cells)
    "link_bytes_up",
    # CPU seconds (utime + stime) over the measured window: the CEDDP's process and the
    # robots' processes summed (lab cells of both middlewares)
    "cpu_s_ceddp",
    "cpu_s_robots",
    "measured_s",
    "wall_s",
    "rrd",
    "error",
)


#: the middleware of a row written before results.csv had the column
DEFAULT_MIDDLEWARE = "arpz"

CellKey = tuple[str, str, str, str, str, str]


def _cell_key(row: Mapping[str, str]) -> CellKey:
    return (
        row["rmax_hz"],
        row["depth"],
        row["config"],
        row["repeat"],
        row["network"],
        row.get("middleware") or DEFAULT_MIDDLEWARE,
    )


def _header(path: Path) -> tuple[str, ...]:
    with path.open(newline="", encoding="utf-8") as handle:
        return tuple(next(csv.reader(handle), []))


def _complete_rows(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    """The header and every complete row of ``path``, in file order; a row of a file written
    before a column existed gets "" for it (so readers can index every column of COLUMNS)."""
    with path.open(newline="", encoding="utf-8") as handle:
        reader = csv.DictReader(handle)
        rows = [r for r in reader if r.get("status") and None not in r.values()]
        header = list(reader.fieldnames or [])
    for row in rows:
        for column in COLUMNS:
            row.setdefault(column, "")
        row["middleware"] = row["middleware"] or DEFAULT_MIDDLEWARE
    return header, rows


def read_rows(path: Path) -> list[dict[str, str]]:
    """Every complete row of ``path`` (none if it does not exist); later rows for the same cell
    (a retried failure) replace earlier ones. Columns the file predates read as ""."""
    if not path.exists():
        return []
    _, rows = _complete_rows(path)
    latest: dict[CellKey, dict[str, str]] = {}
    for row in rows:
        latest[_cell_key(row)] = row
    return list(latest.values())


def upgrade_header(path: Path) -> bool:
    """Rewrite a results.csv written with other columns (an older version) with today's,
    atomically, every complete row kept in order and columns it lacked empty, so rows appended
    by a resumed run line up with the header. Columns no longer written are dropped. True if
    the file was rewritten."""
    if not path.exists() or path.stat().st_size == 0:
        return False
    header, rows = _complete_rows(path)
    if tuple(header) == COLUMNS:
        return False
    tmp = path.with_suffix(".csv.upgrade")
    with tmp.open("w", encoding="utf-8", newline="") as handle:
        writer = csv.DictWriter(
            handle, fieldnames=COLUMNS, lineterminator="\n", extrasaction="ignore"
        )
        writer.writeheader()
        writer.writerows(rows)
        handle.flush()
        os.fsync(handle.fileno())
    tmp.replace(path)
    return True


def done_keys(path: Path) -> set[CellKey]:
    """Cells that finished (status ok or failed-mission): a rerun skips them; errors are retried."""
    return {_cell_key(r) for r in read_rows(path) if r["status"] == "ok"}


def _text(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.4g}" if abs(value) < 1e6 else f"{value:.0f}"
    return str(value)


def append_row(path: Path, row: Mapping[str, Any]) -> None:
    """Append one complete line (header first if the file is new), flushed to disk."""
    unknown = set(row) - set(COLUMNS)
    if unknown:
        raise ValueError(f"unknown results.csv columns: {sorted(unknown)}")
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=COLUMNS, lineterminator="\n")
    new = not path.exists() or path.stat().st_size == 0
    if not new and _header(path) != COLUMNS:
        upgrade_header(path)  # resuming a results.csv of an older version
    if new:
        writer.writeheader()
    writer.writerow({k: _text(row.get(k)) for k in COLUMNS})
    with path.open("a", encoding="utf-8", newline="") as handle:
        handle.write(buffer.getvalue())
        handle.flush()
        os.fsync(handle.fileno())


def _pct(part: float, whole: float) -> float | None:
    return 100.0 * part / whole if whole else None


def _sum(rows: Iterable[Mapping[str, Any]], key: str) -> int:
    return int(sum(int(r.get(key) or 0) for r in rows))


def _count(value: Any) -> int:
    return int(value or 0)


def _sum_known(
    rows: Iterable[Mapping[str, Any]], key: str, measure: Callable[[Any], int] = _count
) -> int | None:
    """The sum of ``measure(row[key])``, or None when no row has ``key`` (a summary from before
    it existed)."""
    present = [r[key] for r in rows if key in r]
    return sum(measure(v) for v in present) if present else None


def _median(values: list[float]) -> float | None:
    return statistics.median(values) if values else None


def _max(values: Iterable[float | None]) -> float | None:
    present = [v for v in values if v is not None]
    return max(present) if present else None


def staleness(robots: Iterable[Mapping[str, Any]]) -> dict[str, float | None]:
    """The fleet's staleness over the robots' sensor topics (not the Hello probe).

    The summary gives, per topic, p50, p99 and max, and per robot a p99 pooled over its sensor
    topics (no pooled p50, no fleet-wide pool). ``staleness_ms_max`` is the maximum over every
    topic, exact; ``staleness_ms_p99`` the worst robot's pooled p99 (a robot without it: the
    maximum of its topics' p99), as ``sample_latency_ms_p99`` is the worst robot's;
    ``staleness_ms_p50`` the median of the per-topic p50s (a typical topic's median)."""
    p50s: list[float] = []
    p99s: list[float | None] = []
    maxima: list[float | None] = []
    for robot in robots:
        sensors = [t for name, t in (robot.get("topics") or {}).items() if name != "hello"]
        p50s += [t["staleness_ms_p50"] for t in sensors if t.get("staleness_ms_p50") is not None]
        topic_p99 = _max(t.get("staleness_ms_p99") for t in sensors)
        pooled = robot.get("staleness_ms_p99")
        p99s.append(pooled if pooled is not None else topic_p99)
        maxima += [t.get("staleness_ms_max") for t in sensors]
    return {
        "staleness_ms_p50": _median(p50s),
        "staleness_ms_p99": _max(p99s),
        "staleness_ms_max": _max(maxima),
    }


def downlink(robots: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """CEDDP -> robot counters summed over the fleet, split into Hello hops and other commands.

    ``downlink_reconciled``: every robot command key that reached a matched reader (written
    minus unmatched minus write failures > 0) was reconciled by the CEDDP's summary (the robot's
    delivered + lost + lifespan-expired covers what this CEDDP's writer sent it);
    ``downlink_unreconciled`` lists the others as ``robot/command``. Both empty when the
    summary has no downlink (a CEDDP older than issue 14, or nothing written); "plain" when
    every command key was a plain put (``plain_downlink``: no channel, nothing to reconcile)."""
    out: dict[str, Any] = {}
    for prefix in ("hello_hops", "commands"):
        for field in ("written", "delivered", "lost"):
            out[f"{prefix}_{field}"] = 0
    unreconciled: list[str] = []
    seen = through_channel = False
    for robot, row in sorted(robots.items()):
        for name, c in sorted((row.get("downlink") or {}).items()):
            seen = True
            prefix = "hello_hops" if name == "hello" else "commands"
            for field in ("written", "delivered", "lost"):
                out[f"{prefix}_{field}"] += int(c.get(field) or 0)
            reached = (
                int(c.get("written") or 0)
                - int(c.get("unmatched") or 0)
                - int(c.get("write_failures") or 0)
            )
            if c.get("channel") is False:
                continue  # a plain put: the robot's seq gaps are its only account
            through_channel = True
            if reached > 0 and c.get("reconciled") is not True:
                unreconciled.append(f"{robot}/{name}")
    if not seen:
        return dict.fromkeys(out) | {"downlink_reconciled": None, "downlink_unreconciled": None}
    if not through_channel:
        return out | {"downlink_reconciled": "plain", "downlink_unreconciled": ""}
    out["downlink_reconciled"] = "no" if unreconciled else "yes"
    out["downlink_unreconciled"] = ";".join(unreconciled)
    return out


def hello_columns(hello: Mapping[str, Any]) -> dict[str, Any]:
    """The Hello round trip's columns from the origin robot's Hello counters (arpz's
    ``HelloStats`` fields; empty when there was no Hello)."""
    sent = int(hello.get("sent") or 0)
    return {
        "latency_ms_p50": hello.get("rtt_ms_p50"),
        "latency_ms_p99": hello.get("rtt_ms_p99"),
        "loss_pct": _pct(int(hello.get("lost") or 0), sent),
        "hello_sent": sent if hello else None,
        "hello_received": hello.get("received"),
        "hello_lost": hello.get("lost"),
    }


def cell_identity(cell: Cell, experiment: str) -> dict[str, Any]:
    return {
        "experiment": experiment,
        "rmax_hz": format_rate(cell.rmax_hz),
        "depth": cell.depth,
        "config": cell.config,
        "repeat": cell.repeat,
        "network": cell.network,
        "middleware": cell.middleware,
    }


def row_from_summary(
    cell: Cell,
    summary: Mapping[str, Any],
    *,
    experiment: str,
    link: Mapping[str, int],
    measured_s: float,
    wall_s: float,
    rrd: str,
    configured: tuple[float, int] | None = None,
    cpu_s: Mapping[str, float] | None = None,
) -> dict[str, Any]:
    """The results.csv row of a finished cell, from the CEDDP's summary.json.

    ``configured``: the (rate, depth) the robots were configured with (fleet.configured_qos),
    recorded as the QoS used when the CEDDP assigned none (all but opt); without it, Rmax and
    the cell's depth. ``cpu_s``: CPU seconds per process over the window (lab cells)."""
    robots: dict[str, Any] = dict(summary.get("robots") or {})
    rows = list(robots.values())
    hello = (robots.get("robot1") or {}).get("hello") or {}
    topics = [t for r in rows for name, t in (r.get("topics") or {}).items() if name != "hello"]
    sent = _sum(rows, "sent")
    lost = _sum(rows, "lost")
    p50s = [r["latency_ms_p50"] for r in rows if r.get("latency_ms_p50") is not None]
    p99s = [r["latency_ms_p99"] for r in rows if r.get("latency_ms_p99") is not None]
    qos = summary.get("qos") or {}
    assignments = qos.get("assignments") or []
    if assignments:
        # the assignment in force while the whole fleet ran: the last one for the most robots
        # (robots leaving at shutdown cause later ones for fewer robots)
        most = max(len(a["robots"]) for a in assignments)
        in_force = [a for a in assignments if len(a["robots"]) == most][-1]
        chosen = in_force["robots"].get("robot1") or next(iter(in_force["robots"].values()))
        rate_hz = float(chosen["rate_hz"])
        depth = int(chosen["depth"])
        deadline_ms = 1000.0 * float(chosen["deadline_s"])
        acks = qos.get("acks") or {}
        # a robot's last answer is kept: one that applied this epoch or a later one applied it
        applied = sum(
            1
            for robot, a in acks.items()
            if robot in in_force["robots"]
            and a.get("status") == "applied"
            and int(a.get("epoch") or 0) >= int(in_force["epoch"])
        )
    else:
        rate_hz, depth = configured or (
            cell.rmax_hz,
            int(cell.depth) if str(cell.depth).isdigit() else 0,
        )
        deadline_ms = 1000.0 / rate_hz
        applied = 0
    mission = summary.get("mission") or {}
    result = mission.get("result") if isinstance(mission, dict) else None
    return {
        **cell_identity(cell, experiment),
        "status": "ok",
        **hello_columns(hello),
        "sample_latency_ms_p50": max(p50s) if p50s else None,
        "sample_latency_ms_p99": max(p99s) if p99s else None,
        **clock(rows),
        "sample_loss_pct": _pct(lost, sent),
        "samples_produced": _sum(rows, "produced"),
        "samples_sent": sent,
        "samples_held_back": _sum(rows, "held_back"),
        "samples_write_failures": _sum(rows, "write_failures"),
        "samples_received": _sum(rows, "received"),
        "samples_lost": lost,
        "samples_discarded": _sum(rows, "cc_discarded"),
        "samples_retransmitted": _sum(rows, "retransmitted"),
        "samples_overwritten_unacked": _sum(topics, "overwritten_unacked"),
        "final_reports": sum(1 for r in rows if r.get("final_stats")),
        "rate_hz": rate_hz,
        "qos_depth": depth,
        "deadline_ms": deadline_ms,
        "qos_epochs": len(assignments),
        "qos_applied": applied,
        **staleness(rows),
        "cache_forgets": _sum_known(topics, "cache_forgets"),
        **downlink(robots),
        "commands_expired": _sum_known(rows, "commands_expired"),
        "watchdog_stops": _sum_known(rows, "watchdog_stops", lambda v: sum((v or {}).values())),
        "incompatible_qos": _sum_known(rows, "incompatible_qos", lambda v: len(v or [])),
        "samples_refused": _sum_known(rows, "refused"),
        # a mission with no verdict (it never started: a robot missing) failed too
        "mission": (result or {}).get("mission", "failure") if mission else None,
        "mission_reason": (result or {}).get("reason", "no verdict: the mission never started")
        if mission
        else None,
        "mission_duration_s": (result or {}).get("duration_s") if mission else None,
        "link_datagrams": link.get("received", 0),
        "link_dropped": link.get("dropped", 0),
        "link_loss_pct": _pct(link.get("dropped", 0), link.get("received", 0)),
        "link_bytes_up": link.get("bytes_up"),
        **cpu_columns(cpu_s or {}),
        "measured_s": measured_s,
        "wall_s": wall_s,
        "rrd": rrd,
    }


def cpu_columns(cpu_s: Mapping[str, float]) -> dict[str, float | None]:
    """``cpu_s_ceddp`` and ``cpu_s_robots`` (the robots' processes summed); None when the
    process was not measured (proxy cells)."""
    robots = [v for name, v in cpu_s.items() if name != "ceddp"]
    return {
        "cpu_s_ceddp": cpu_s.get("ceddp"),
        "cpu_s_robots": sum(robots) if robots else None,
    }


def clock(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Whether every robot's sample latency was corrected by its clock offset, and the largest
    |offset| (None: no robot reported one, e.g. a summary from before clock offsets)."""
    offsets = [
        abs(float(r["clock"]["offset_ms"]))
        for r in rows
        if isinstance(r.get("clock"), dict) and r["clock"].get("offset_ms") is not None
    ]
    return {
        "clock_corrected": bool(rows) and all(r.get("clock_corrected") for r in rows),
        "clock_offset_ms_max": max(offsets) if offsets else None,
    }


def error_row(cell: Cell, *, experiment: str, error: str, wall_s: float) -> dict[str, Any]:
    return {
        **cell_identity(cell, experiment),
        "status": "error",
        "wall_s": wall_s,
        "error": " ".join(error.split())[:400],
    }


def _saved_spec(directory: Path) -> ExperimentSpec | None:
    """The spec the run wrote to DIR/spec.json (None if absent or unreadable)."""
    try:
        return msgspec.json.decode((directory / "spec.json").read_bytes(), type=ExperimentSpec)
    except (OSError, msgspec.DecodeError, msgspec.ValidationError):
        return None


def _configured(
    spec: ExperimentSpec | None, cell: Cell, row: Mapping[str, str]
) -> tuple[float, int] | None:
    """The (rate, depth) the cell's robots were configured with: from the spec if it is known,
    else what the row already says."""
    from arpz.experiment.fleet import configured_qos

    if spec is not None:
        try:
            return configured_qos(spec, cell)
        except SpecError:
            pass
    if row.get("rate_hz") and row.get("qos_depth"):
        return float(row["rate_hz"]), int(row["qos_depth"])
    return None


def refresh_rows(directory: Path) -> int:
    """Re-derive every ok row from its cell's kept ``runs/<cell>/summary.json`` (after a change
    to how rows are computed), keeping what only the runner knew (link counters, timings);
    results.csv is replaced atomically. Returns the number of rows refreshed."""
    path = directory / "results.csv"
    rows = read_rows(path)
    spec = _saved_spec(directory)
    refreshed = 0
    out: list[dict[str, Any]] = []
    for row in rows:
        depth: int | str = int(row["depth"]) if row["depth"].isdigit() else row["depth"]
        cell = Cell(
            float(row["rmax_hz"]),
            depth,
            row["config"],
            int(row["repeat"]),
            row["network"],
            row["middleware"],
        )
        summary_path = directory / "runs" / cell.slug / "summary.json"
        if row["status"] != "ok" or cell.middleware != "arpz" or not summary_path.exists():
            out.append(dict(row))
            continue
        new = row_from_summary(
            cell,
            json.loads(summary_path.read_text(encoding="utf-8")),
            experiment=row["experiment"],
            link={
                "received": int(row["link_datagrams"] or 0),
                "dropped": int(row["link_dropped"] or 0),
            },
            measured_s=float(row["measured_s"] or 0),
            wall_s=float(row["wall_s"] or 0),
            rrd=row["rrd"],
            configured=_configured(spec, cell, row),
            cpu_s={
                name: float(row[column])
                for name, column in (("ceddp", "cpu_s_ceddp"), ("robots", "cpu_s_robots"))
                if row[column]
            },
        )
        out.append(new)
        refreshed += 1
    tmp = path.with_suffix(".csv.tmp")
    tmp.unlink(missing_ok=True)
    for row in out:
        append_row(tmp, row)
    tmp.replace(path)
    return refreshed
