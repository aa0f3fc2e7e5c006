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
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from arpz.experiment.spec import Cell, format_rate

COLUMNS: tuple[str, ...] = (
    "experiment",
    "rmax_hz",
    "depth",
    "config",
    "repeat",
    "network",
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
    "qos_depth",
    "deadline_ms",
    "qos_epochs",
    "qos_applied",
    # the hallway mission (seed 001 Fig. 16); empty for the sensor fleet
    "mission",
    "mission_reason",
    "mission_duration_s",
    # what the emulated links did (both directions, all robots)
    "link_datagrams",
    "link_dropped",
    "link_loss_pct",
    "measured_s",
    "wall_s",
    "rrd",
    "error",
)


def _cell_key(row: Mapping[str, str]) -> tuple[str, str, str, str, str]:
    return (row["rmax_hz"], row["depth"], row["config"], row["repeat"], row["network"])


def read_rows(path: Path) -> list[dict[str, str]]:
    """Every complete row of ``path`` (none if it does not exist); later rows for the same cell
    (a retried failure) replace earlier ones."""
    if not path.exists():
        return []
    with path.open(newline="", encoding="utf-8") as handle:
        rows = [r for r in csv.DictReader(handle) if r.get("status") and None not in r.values()]
    latest: dict[tuple[str, str, str, str, str], dict[str, str]] = {}
    for row in rows:
        latest[_cell_key(row)] = row
    return list(latest.values())


def done_keys(path: Path) -> set[tuple[str, str, str, str, str]]:
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


def _identity(cell: Cell, experiment: str) -> dict[str, Any]:
    return {
        "experiment": experiment,
        "rmax_hz": format_rate(cell.rmax_hz),
        "depth": cell.depth,
        "config": cell.config,
        "repeat": cell.repeat,
        "network": cell.network,
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
) -> dict[str, Any]:
    """The results.csv row of a finished cell, from the CEDDP's summary.json."""
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
        rate_hz = cell.rmax_hz
        depth = int(cell.depth) if str(cell.depth).isdigit() else 0
        deadline_ms = 1000.0 / cell.rmax_hz
        applied = 0
    mission = summary.get("mission") or {}
    result = mission.get("result") if isinstance(mission, dict) else None
    hello_sent = int(hello.get("sent") or 0)
    return {
        **_identity(cell, experiment),
        "status": "ok",
        "latency_ms_p50": hello.get("rtt_ms_p50"),
        "latency_ms_p99": hello.get("rtt_ms_p99"),
        "loss_pct": _pct(int(hello.get("lost") or 0), hello_sent),
        "hello_sent": hello_sent if hello else None,
        "hello_received": hello.get("received"),
        "hello_lost": hello.get("lost"),
        "sample_latency_ms_p50": max(p50s) if p50s else None,
        "sample_latency_ms_p99": max(p99s) if p99s else None,
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
        # a mission with no verdict (it never started: a robot missing) failed too
        "mission": (result or {}).get("mission", "failure") if mission else None,
        "mission_reason": (result or {}).get("reason", "no verdict: the mission never started")
        if mission
        else None,
        "mission_duration_s": (result or {}).get("duration_s") if mission else None,
        "link_datagrams": link.get("received", 0),
        "link_dropped": link.get("dropped", 0),
        "link_loss_pct": _pct(link.get("dropped", 0), link.get("received", 0)),
        "measured_s": measured_s,
        "wall_s": wall_s,
        "rrd": rrd,
    }


def error_row(cell: Cell, *, experiment: str, error: str, wall_s: float) -> dict[str, Any]:
    return {
        **_identity(cell, experiment),
        "status": "error",
        "wall_s": wall_s,
        "error": " ".join(error.split())[:400],
    }


def refresh_rows(directory: Path) -> int:
    """Re-derive every ok row from its cell's kept ``runs/<cell>/summary.json`` (after a change
    to how rows are computed), keeping what only the runner knew (link counters, timings);
    results.csv is replaced atomically. Returns the number of rows refreshed."""
    path = directory / "results.csv"
    rows = read_rows(path)
    refreshed = 0
    out: list[dict[str, Any]] = []
    for row in rows:
        depth: int | str = int(row["depth"]) if row["depth"].isdigit() else row["depth"]
        cell = Cell(float(row["rmax_hz"]), depth, row["config"], int(row["repeat"]), row["network"])
        summary_path = directory / "runs" / cell.slug / "summary.json"
        if row["status"] != "ok" or not summary_path.exists():
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
        )
        out.append(new)
        refreshed += 1
    tmp = path.with_suffix(".csv.tmp")
    tmp.unlink(missing_ok=True)
    for row in out:
        append_row(tmp, row)
    tmp.replace(path)
    return refreshed
