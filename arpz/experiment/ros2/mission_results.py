"""The side-by-side results of the hallway mission (Figure 16) over ROS 2 and over arpz: one CSV
row per mission and middleware, arpz's rows taken from ``arpz.experiment``'s results.csv, the
verdict table (markdown) and the figure (Figure 16's counts of success, timeout and collision
per Rmax, depth and configuration, both middlewares side by side).
"""

from __future__ import annotations

import csv
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from arpz.experiment.ros2.mission_parts import verdict_letter

COLUMNS: tuple[str, ...] = (
    "middleware",
    "rmax_hz",
    "depth",
    "config",
    "network",
    "repeat",
    "status",
    "rate_hz",
    "qos_depth",
    "verdict",
    "mission",
    "reason",
    "duration_s",
    "beams_sent",
    "beams_received",
    "beams_lost",
    "beam_loss_pct",
    "beams_due",
    "beam_write_failures",
    "beam_latency_ms_p50",
    "beam_latency_ms_p99",
    "commands_sent",
    "commands_received",
    "watchdog_stops",
    "link_frames",
    "link_dropped",
    "cpu_ceddp_s",
    "cpu_robots_s",
    "wall_s",
    "error",
)
#: the outcomes Figure 16 counts, and the rest (P: a phantom obstacle stop, N: no verdict)
VERDICTS = ("S", "T", "C", "P", "N")
VERDICT_NAMES = {
    "S": "success",
    "T": "timeout",
    "C": "collision",
    "P": "phantom stop",
    "N": "no verdict",
}
MIDDLEWARES = ("ros2", "arpz")


def append_row(path: Path, row: Mapping[str, Any]) -> None:
    """Append ``row`` (COLUMNS; missing ones empty) to the CSV, writing the header first; a
    file written before a column existed is rewritten with every column (empty where unknown)."""
    if path.exists() and _header(path) != COLUMNS:
        old = read_rows(path)
        path.unlink()
        for previous in old:
            append_row(path, previous)
    new = not path.exists()
    with path.open("a", encoding="utf-8", newline="") as handle:
        writer = csv.DictWriter(
            handle, fieldnames=COLUMNS, lineterminator="\n", extrasaction="ignore"
        )
        if new:
            writer.writeheader()
        writer.writerow({column: row.get(column, "") for column in COLUMNS})


def _header(path: Path) -> tuple[str, ...]:
    with path.open(encoding="utf-8", newline="") as handle:
        return tuple(next(csv.reader(handle), []))


def read_rows(path: Path) -> list[dict[str, str]]:
    if not path.exists():
        return []
    with path.open(encoding="utf-8", newline="") as handle:
        return list(csv.DictReader(handle))


def error_row(middleware: str, key: Mapping[str, Any], error: str, wall_s: float) -> dict[str, Any]:
    return {
        **key,
        "middleware": middleware,
        "status": "error",
        "error": error,
        "wall_s": round(wall_s, 1),
    }


def arpz_row(
    row: Mapping[str, str], cpu: Mapping[str, float], *, wall_s: float | None = None
) -> dict[str, Any]:
    """Our row of one of arpz.experiment's results.csv rows (a lab mission cell), with the
    CPU seconds of its processes (``ceddp`` and the robots' sum) measured from /proc."""
    status = (
        "ok" if row.get("status") in ("ok", "failed-mission") or row.get("mission") else "error"
    )
    result = {"mission": row.get("mission", ""), "reason": row.get("mission_reason", "")}
    return {
        "middleware": "arpz",
        "rmax_hz": row["rmax_hz"],
        "depth": row["depth"],
        "config": row["config"],
        "network": row["network"],
        "repeat": row["repeat"],
        "status": status,
        "rate_hz": row.get("rate_hz", ""),
        "qos_depth": row.get("qos_depth", ""),
        "verdict": verdict_letter(result) if row.get("mission") else "N",
        "mission": row.get("mission", ""),
        "reason": row.get("mission_reason", ""),
        "duration_s": row.get("mission_duration_s", ""),
        "beams_sent": row.get("samples_sent", ""),
        "beams_received": row.get("samples_received", ""),
        "beams_lost": row.get("samples_lost", ""),
        "beam_loss_pct": row.get("sample_loss_pct", ""),
        "beam_write_failures": row.get("samples_write_failures", ""),
        "beam_latency_ms_p50": row.get("sample_latency_ms_p50", ""),
        "beam_latency_ms_p99": row.get("sample_latency_ms_p99", ""),
        "commands_sent": row.get("commands_written", ""),
        "commands_received": row.get("commands_delivered", ""),
        "watchdog_stops": row.get("watchdog_stops", ""),
        "link_frames": row.get("link_datagrams", ""),
        "link_dropped": row.get("link_dropped", ""),
        "cpu_ceddp_s": round(cpu.get("ceddp", 0.0), 2),
        "cpu_robots_s": round(sum(v for k, v in cpu.items() if k != "ceddp"), 2),
        "wall_s": row.get("wall_s", "") if wall_s is None else round(wall_s, 1),
        "error": row.get("error", ""),
    }


def group_key(row: Mapping[str, Any]) -> tuple[float, str, str]:
    """(Rmax, depth, config): a point of Figure 16."""
    return (float(row["rmax_hz"]), str(row["depth"]), str(row["config"]))


def column_label(depth: str, config: str) -> str:
    return "OPT (Opt(R), Opt(D))" if config == "opt" else f"no opt., depth {depth}"


def tally(
    rows: Iterable[Mapping[str, Any]],
) -> dict[tuple[str, tuple[float, str, str]], Counter[str]]:
    """Verdict counts per (middleware, Figure 16 point), ok rows only."""
    counts: dict[tuple[str, tuple[float, str, str]], Counter[str]] = {}
    for row in rows:
        if row.get("status") != "ok":
            continue
        counts.setdefault((str(row["middleware"]), group_key(row)), Counter())[
            str(row["verdict"])
        ] += 1
    return counts


def _points(rows: Sequence[Mapping[str, Any]]) -> list[tuple[float, str, str]]:
    def order(point: tuple[float, str, str]) -> tuple[float, int, int]:
        rmax, depth, config = point
        return (rmax, config == "opt", int(depth) if depth.isdigit() else 0)

    return sorted({group_key(r) for r in rows}, key=order)


def _counts_text(counts: Counter[str] | None) -> str:
    if not counts:
        return "-"
    return " ".join(f"{counts[v]}{v}" for v in VERDICTS if counts[v])


def verdict_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """Markdown: one line per Figure 16 point, the verdict counts of each middleware, the beam
    loss and the CPU seconds (planner + robots), means over the ok rows."""
    counts = tally(rows)
    lines = [
        "| Rmax (Hz) | configuration | R, D | ROS 2 verdicts | arpz verdicts | ROS 2 beams lost | "
        "arpz beams lost | ROS 2 beam latency p99 | arpz beam latency p99 | "
        "ROS 2 CPU s (planner + robots) | arpz CPU s (CEDDP + robots) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for point in _points(rows):
        rmax, depth, config = point
        by = {
            m: [
                r
                for r in rows
                if r["middleware"] == m and group_key(r) == point and r.get("status") == "ok"
            ]
            for m in MIDDLEWARES
        }
        qos = next((f"{r['rate_hz']} Hz, {r['qos_depth']}" for m in MIDDLEWARES for r in by[m]), "")
        lines.append(
            f"| {rmax:g} | {column_label(depth, config)} | {qos} | "
            f"{_counts_text(counts.get(('ros2', point)))} | "
            f"{_counts_text(counts.get(('arpz', point)))} | "
            f"{_mean_pct(by['ros2'])} | {_mean_pct(by['arpz'])} | "
            f"{_mean_ms(by['ros2'])} | {_mean_ms(by['arpz'])} | "
            f"{_cpu(by['ros2'])} | {_cpu(by['arpz'])} |"
        )
    return "\n".join(lines)


def _number(value: Any) -> float | None:
    try:
        return float(value)
    except (TypeError, ValueError):
        return None


def _mean_pct(rows: Sequence[Mapping[str, Any]]) -> str:
    values = [v for v in (_number(r.get("beam_loss_pct")) for r in rows) if v is not None]
    return f"{sum(values) / len(values):.1f} %" if values else "-"


def _mean_ms(rows: Sequence[Mapping[str, Any]]) -> str:
    values = [v for v in (_number(r.get("beam_latency_ms_p99")) for r in rows) if v is not None]
    return f"{sum(values) / len(values):.0f} ms" if values else "-"


def _cpu(rows: Sequence[Mapping[str, Any]]) -> str:
    pairs = [(_number(r.get("cpu_ceddp_s")), _number(r.get("cpu_robots_s"))) for r in rows]
    pairs = [(a, b) for a, b in pairs if a is not None and b is not None]
    if not pairs:
        return "-"
    ceddp = sum(a for a, _ in pairs if a is not None) / len(pairs)
    robots = sum(b for _, b in pairs if b is not None) / len(pairs)
    return f"{ceddp:.0f} + {robots:.0f}"


def draw_figure(rows: Sequence[Mapping[str, Any]], path: Path, *, title: str) -> Path:
    """Figure 16's layout: one panel per Rmax, a pair of stacked bars (ROS 2, arpz) per depth
    and configuration, stacked by verdict."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    counts = tally(rows)
    points = _points(rows)
    rates = sorted({p[0] for p in points})
    colours = {"S": "#2e7d32", "T": "#f9a825", "C": "#c62828", "P": "#6a1b9a", "N": "#9e9e9e"}
    fig, axes = plt.subplots(
        1, len(rates), figsize=(4.2 * len(rates), 4.0), squeeze=False, sharey=True
    )
    for ax, rate in zip(axes[0], rates, strict=True):
        columns = [p for p in points if p[0] == rate]
        for index, point in enumerate(columns):
            for offset, middleware in ((-0.2, "ros2"), (0.2, "arpz")):
                bottom = 0
                tallied = counts.get((middleware, point), Counter())
                for verdict in VERDICTS:
                    n = tallied[verdict]
                    if n:
                        ax.bar(
                            index + offset,
                            n,
                            0.38,
                            bottom=bottom,
                            color=colours[verdict],
                            edgecolor="black",
                            hatch="//" if middleware == "ros2" else None,
                        )
                        bottom += n
        ax.set_xticks(range(len(columns)))
        ax.set_xticklabels(
            [column_label(d, c).replace(", ", "\n") for _, d, c in columns], fontsize=8
        )
        ax.set_title(f"Rmax = {rate:g} Hz")
        ax.set_ylabel("missions")
        ax.yaxis.get_major_locator().set_params(integer=True)
    handles = [Rectangle((0, 0), 1, 1, color=colours[v]) for v in VERDICTS]
    handles += [
        Rectangle((0, 0), 1, 1, facecolor="white", edgecolor="black", hatch="//"),
        Rectangle((0, 0), 1, 1, facecolor="white", edgecolor="black"),
    ]
    fig.legend(
        handles,
        [VERDICT_NAMES[v] for v in VERDICTS] + ["ROS 2 (left bar)", "arpz (right bar)"],
        loc="lower center",
        ncol=len(VERDICTS) + 2,
        fontsize=8,
    )
    fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.07, 1, 0.95))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
