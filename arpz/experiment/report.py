"""Figures and REPORT.md from results.csv alone (``python -m arpz.experiment report DIR``).

The figures follow seed 001's bar charts: one panel per Rmax, DEPTH groups on the x axis
(1 ... 5000, then Opt(D)), one bar per configuration. A bar is the mean over the cell's repeats
with a whisker from the lowest to the highest repeat and a dot per repeat (mission success: the
share of successful repeats, whisker the Wilson 95 % interval of that share). Nothing here
reruns or reads anything but the CSV, so results can be re-plotted, merged from several
machines, or checked by a reviewer.

When a results file holds both middlewares (``middleware = ["arpz", "ros2"]``), a bar is a
middleware and a configuration ("arpz no opt.", "ROS 2 OPT" ...): the same panels and groups,
arpz's bars first, so each DEPTH group shows both side by side. Results of one middleware are
reported exactly as before.
"""

from __future__ import annotations

import math
import statistics
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.axes import Axes
from matplotlib.ticker import NullFormatter, ScalarFormatter

from arpz.core.errors import ArpzError
from arpz.experiment.results import read_rows
from arpz.experiment.spec import FEATURES, OPT_DEPTH, OPT_VARIANTS, config_label

Row = dict[str, str]


class ReportError(ArpzError):
    """No results to report (or an unreadable results.csv)."""


@dataclass(frozen=True)
class Spread:
    """One bar: its height, its whisker and the repeats behind it."""

    value: float
    low: float
    high: float
    #: the per-repeat values (mission: 100 for a success, 0 for a failure)
    points: tuple[float, ...]

    @property
    def n(self) -> int:
        return len(self.points)


def _floats(rows: Sequence[Row], column: str) -> list[float]:
    return [float(r[column]) for r in rows if r.get(column) not in (None, "")]


def _mean(column: str) -> Callable[[Sequence[Row]], float | None]:
    def value(rows: Sequence[Row]) -> float | None:
        values = _floats(rows, column)
        return statistics.fmean(values) if values else None

    return value


def _range(column: str) -> Callable[[Sequence[Row]], Spread | None]:
    """Mean of the repeats, whisker min..max."""

    def spread(rows: Sequence[Row]) -> Spread | None:
        values = _floats(rows, column)
        if not values:
            return None
        return Spread(statistics.fmean(values), min(values), max(values), tuple(values))

    return spread


#: z of a two-sided 95 % interval
Z95 = 1.959963984540054


def wilson(successes: int, n: int, z: float = Z95) -> tuple[float, float]:
    """The Wilson score interval of a proportion (0..1): sensible at 0/n and n/n, unlike the
    normal approximation, which is what a few repeats of a mission give."""
    if n <= 0:
        return (0.0, 1.0)
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    # exact at the ends (rounding would put 0 successes a hair above 0)
    low = 0.0 if successes == 0 else max(0.0, min(p, centre - half))
    high = 1.0 if successes == n else min(1.0, max(p, centre + half))
    return (low, high)


def _success_spread(rows: Sequence[Row]) -> Spread | None:
    verdicts = [r["mission"] for r in rows if r.get("mission")]
    if not verdicts:
        return None
    wins = sum(v == "success" for v in verdicts)
    low, high = wilson(wins, len(verdicts))
    points = tuple(100.0 if v == "success" else 0.0 for v in verdicts)
    return Spread(100.0 * wins / len(verdicts), 100.0 * low, 100.0 * high, points)


def _success(rows: Sequence[Row]) -> float | None:
    spread = _success_spread(rows)
    return None if spread is None else spread.value


@dataclass(frozen=True)
class Metric:
    key: str
    title: str
    unit: str
    spread: Callable[[Sequence[Row]], Spread | None]
    log: bool = False
    #: how the whisker is computed, for the figure's caption
    whisker: str = "min-max of the repeats"
    #: the y axis label (short: the title says the rest)
    axis: str = ""

    def value(self, rows: Sequence[Row]) -> float | None:
        spread = self.spread(rows)
        return None if spread is None else spread.value


METRICS: tuple[Metric, ...] = (
    Metric(
        "latency",
        "Hello round-trip latency (p50)",
        "ms",
        _range("latency_ms_p50"),
        log=True,
        axis="Hello RTT p50",
    ),
    Metric("loss", "Hello packet loss", "%", _range("loss_pct"), axis="Hello loss"),
    Metric(
        "sample_latency",
        "sensor sample latency (p50, worst robot)",
        "ms",
        _range("sample_latency_ms_p50"),
        log=True,
        axis="sample latency p50",
    ),
    Metric("sample_loss", "sensor sample loss", "%", _range("sample_loss_pct"), axis="sample loss"),
    Metric(
        "staleness",
        "sensor value staleness at the CEDDP (p99, worst robot)",
        "ms",
        _range("staleness_ms_p99"),
        log=True,
        axis="staleness p99",
    ),
    Metric(
        "mission",
        "mission success",
        "%",
        _success_spread,
        whisker="Wilson 95 % interval of the share",
        axis="mission success",
    ),
)


def _depth_order(depth: str) -> tuple[int, int]:
    return (1, 0) if depth == OPT_DEPTH else (0, int(depth))


def _depth_label(depth: str) -> str:
    return "Opt(D)" if depth == OPT_DEPTH else depth


def _config_order(config: str) -> tuple[int, int, str]:
    """baseline, LC, CC ..., then OPT R-only, OPT D-only and OPT, each alone and then combined."""
    parts = config.split("+")
    variant = next((v for v in OPT_VARIANTS if v in parts), None)
    rank = {None: 0, "optr": 1, "optd": 2, "opt": 3}[variant]
    return (
        rank,
        len(parts) if config != "baseline" else 0,
        "".join(str(FEATURES.index(p)) for p in parts if p in FEATURES),
    )


def _rate_key(rate: str) -> float:
    return float(rate)


#: how figures and tables name the middlewares
MIDDLEWARE_LABELS = {"arpz": "arpz", "ros2": "ROS 2"}
#: between a series' middleware and its configuration
_SEP = "|"


def _mixed(rows: Sequence[Row]) -> bool:
    """More than one middleware: every bar names its middleware."""
    return len({r["middleware"] for r in rows}) > 1


def _series(row: Row, mixed: bool) -> str:
    """What a bar stands for: the configuration, or middleware|configuration when mixed."""
    return f"{row['middleware']}{_SEP}{row['config']}" if mixed else row["config"]


def _series_order(series: str) -> tuple[int, tuple[int, int, str]]:
    middleware, _, config = series.rpartition(_SEP)
    rank = list(MIDDLEWARE_LABELS).index(middleware) if middleware in MIDDLEWARE_LABELS else -1
    return (rank, _config_order(config))


def series_label(series: str) -> str:
    """ "no opt.", "LC + OPT" ..., or "ROS 2 OPT" when the series names its middleware."""
    middleware, _, config = series.rpartition(_SEP)
    if not middleware:
        return config_label(config)
    return f"{MIDDLEWARE_LABELS.get(middleware, middleware)} {config_label(config)}"


def _grouped(rows: Sequence[Row]) -> dict[tuple[str, str, str, str], list[Row]]:
    """(network, rmax, depth, series) -> the repeats of that cell (series: ``_series``)."""
    mixed = _mixed(rows)
    groups: dict[tuple[str, str, str, str], list[Row]] = defaultdict(list)
    for row in rows:
        groups[(row["network"], row["rmax_hz"], row["depth"], _series(row, mixed))].append(row)
    return groups


def _bar_panel(
    ax: Axes,
    metric: Metric,
    groups: dict[tuple[str, str, str, str], list[Row]],
    network: str,
    rmax: str,
    configs: list[str],
    depths: list[str],
) -> bool:
    """One of seed 001's panels: DEPTH groups, a bar per configuration measured at that depth
    (a colour per configuration across panels; a zero is written, not left invisible).
    False if there is no data."""
    colours = plt.get_cmap("tab10")
    present = {
        depth: [
            (config, spread)
            for config in configs
            if (cell := groups.get((network, rmax, depth, config)))
            and (spread := metric.spread(cell)) is not None
        ]
        for depth in depths
    }
    widest = max((len(bars) for bars in present.values()), default=0)
    if not widest:
        return False
    width = 0.8 / widest
    floor = 1.0 if metric.log else -math.inf
    labelled: set[str] = set()
    for di, depth in enumerate(depths):
        bars = present[depth]
        for bi, (config, spread) in enumerate(bars):
            x = di + (bi - (len(bars) - 1) / 2) * width
            height = max(spread.value, floor)
            low = min(max(spread.low, floor), height)
            high = max(spread.high, floor, height)
            ax.bar(
                x,
                height,
                width,
                yerr=[[height - low], [high - height]] if spread.n > 1 else None,
                capsize=min(3.0, 60 * width),
                error_kw={"elinewidth": 0.9, "ecolor": "0.15"},
                color=colours(configs.index(config) % 10),
                label=None if config in labelled else series_label(config),
            )
            if spread.n > 1:
                # every repeat, spread across the bar so equal values stay visible
                offsets = [
                    (i - (spread.n - 1) / 2) * width / (spread.n + 1) for i in range(spread.n)
                ]
                ax.scatter(
                    [x + o for o in offsets],
                    [max(p, floor) for p in spread.points],
                    s=6,
                    color="black",
                    zorder=3,
                    linewidths=0,
                )
            labelled.add(config)
            if spread.value == 0 and spread.high == 0:
                ax.text(x, 0, "0", ha="center", va="bottom", fontsize=7)
    ax.set_xticks(range(len(depths)), [_depth_label(d) for d in depths])
    ax.set_xlabel("DEPTH")
    ax.set_ylabel(f"{metric.axis or metric.title} ({metric.unit})")
    ax.set_title(f"Rmax = {rmax} Hz")
    if metric.log:
        # from 1 ms, so bar heights compare; plain numbers on the ticks, not powers of ten
        ax.set_yscale("log")
        ax.set_ylim(bottom=1.0)
        ax.yaxis.set_major_formatter(ScalarFormatter())
        ax.yaxis.set_minor_formatter(NullFormatter())
    if metric.key == "mission":
        ax.set_ylim(0, 105)
    ax.grid(axis="y", alpha=0.3)
    return True


def _caption(
    metric: Metric, groups: dict[tuple[str, str, str, str], list[Row]], network: str
) -> str:
    """What a bar and its whisker are, and over how many repeats."""
    counts = {len(g) for (n, *_), g in groups.items() if n == network}
    if max(counts, default=1) <= 1:
        return "one run per bar (no repeats: no spread)"
    n = str(max(counts)) if len(counts) == 1 else f"{min(counts)}-{max(counts)}"
    what = "share of successes" if metric.key == "mission" else "mean"
    return f"bar: {what} of {n} repeats; whisker: {metric.whisker}; dots: each repeat"


def write_figures(rows: Sequence[Row], figures: Path) -> list[Path]:
    """Per metric and network: one PNG per Rmax and one with every Rmax as panels (a)-(d)."""
    figures.mkdir(parents=True, exist_ok=True)
    groups = _grouped(rows)
    networks = sorted({r["network"] for r in rows})
    rates = sorted({r["rmax_hz"] for r in rows}, key=_rate_key)
    mixed = _mixed(rows)
    configs = sorted({_series(r, mixed) for r in rows}, key=_series_order)
    depths = sorted({r["depth"] for r in rows}, key=_depth_order)
    written: list[Path] = []
    for metric in METRICS:
        for network in networks:
            suffix = f"_{network}" if len(networks) > 1 else ""
            if all(metric.value(g) is None for (n, *_), g in groups.items() if n == network):
                continue
            cols = min(len(rates), 2)
            nrows = math.ceil(len(rates) / cols)
            fig, axes = plt.subplots(nrows, cols, figsize=(6.5 * cols, 4.2 * nrows), squeeze=False)
            for index, rmax in enumerate(rates):
                ax = axes[index // cols][index % cols]
                _bar_panel(ax, metric, groups, network, rmax, configs, depths)
                ax.set_title(f"({chr(ord('a') + index)}) Rmax = {rmax} Hz")
            for index in range(len(rates), nrows * cols):
                axes[index // cols][index % cols].set_visible(False)
            handles, labels = axes[0][0].get_legend_handles_labels()
            for ax in axes.flat:
                h, lab = ax.get_legend_handles_labels()
                for handle, label in zip(h, lab, strict=True):
                    if label not in labels:
                        handles.append(handle)
                        labels.append(label)
            # in inches from the top: the title, then the legend's rows; the caption at the foot
            height = fig.get_figheight()
            ncol = min(len(labels), 4 * cols)
            legend_rows = math.ceil(len(labels) / max(ncol, 1))
            fig.suptitle(
                f"{metric.title}, network {network}", y=1 - 0.08 / height, fontsize="large"
            )
            fig.text(0.5, 0.06 / height, _caption(metric, groups, network), ha="center")
            fig.legend(
                handles,
                labels,
                loc="upper center",
                bbox_to_anchor=(0.5, 1 - 0.4 / height),
                ncol=ncol,
            )
            top = 1 - (0.45 + 0.3 * legend_rows) / height
            fig.tight_layout(rect=(0, 0.3 / height, 1, top))
            path = figures / f"experiment_{metric.key}{suffix}.png"
            fig.savefig(path, dpi=100)
            plt.close(fig)
            written.append(path)
            for rmax in rates:
                fig, ax = plt.subplots(figsize=(7.5, 4.2))
                if _bar_panel(ax, metric, groups, network, rmax, configs, depths):
                    ax.set_title(
                        f"Rmax = {rmax} Hz\n{_caption(metric, groups, network)}",
                        fontsize="small",
                    )
                    ax.legend(
                        fontsize="small",
                        loc="upper center",
                        bbox_to_anchor=(0.5, -0.2),
                        ncol=min(len(configs), 6),
                    )
                    fig.tight_layout()
                    path = figures / f"experiment_{metric.key}_r{rmax}{suffix}.png"
                    fig.savefig(path, dpi=90)
                    written.append(path)
                plt.close(fig)
    return written


def _fmt(value: float | None, digits: int = 3) -> str:
    if value is None:
        return "-"
    return f"{value:.{digits}g}"


def _ranged(rows: Sequence[Row], column: str, digits: int = 3) -> str:
    """The mean over the repeats, and [lowest-highest] when the repeats differ."""
    spread = _range(column)(rows)
    if spread is None:
        return "-"
    low, high = _fmt(spread.low, digits), _fmt(spread.high, digits)
    if spread.n < 2 or low == high:
        return _fmt(spread.value, digits)
    return f"{_fmt(spread.value, digits)} [{low}-{high}]"


def consistency(rows: Sequence[Row]) -> list[str]:
    """Counts that must add up in every ok row: every robot's final counters arrived,
    produced = sent + held back + write failures, sent = received + lost, Hello sent =
    received + lost, and every robot's downlink reconciled (rows that record it)."""
    problems = []
    fleet = max((int(r["final_reports"] or 0) for r in rows if r["status"] == "ok"), default=0)
    for row in rows:
        if row["status"] != "ok":
            continue
        if int(row["final_reports"] or 0) < fleet:
            where = f"Rmax {row['rmax_hz']} depth {row['depth']} {row['config']} {row['network']}"
            problems.append(f"{where}: a robot's final counters never reached the CEDDP")
        n = {k: int(row[k] or 0) for k in row if k.startswith(("samples_", "hello_"))}
        where = f"Rmax {row['rmax_hz']} depth {row['depth']} {row['config']} {row['network']}"
        if row["middleware"] != "arpz":
            where += f" {row['middleware']}"
        if n["samples_produced"] != (
            n["samples_sent"] + n["samples_held_back"] + n["samples_write_failures"]
        ):
            problems.append(f"{where}: produced != sent + held back + write failures")
        if n["samples_sent"] != n["samples_received"] + n["samples_lost"]:
            problems.append(f"{where}: sent != received + lost")
        if row["hello_sent"] and n["hello_sent"] != n["hello_received"] + n["hello_lost"]:
            problems.append(f"{where}: Hello sent != received + lost")
        if row.get("downlink_reconciled") == "no":
            problems.append(
                f"{where}: downlink not reconciled ({row.get('downlink_unreconciled') or '?'})"
            )
    return problems


def markdown(rows: Sequence[Row], figures: Sequence[Path], base: Path) -> str:
    ok = [r for r in rows if r["status"] == "ok"]
    errors = [r for r in rows if r["status"] != "ok"]
    groups = _grouped(ok)
    experiments = sorted({r["experiment"] for r in rows})
    wall = sum(float(r["wall_s"] or 0) for r in rows)
    lines = [
        f"# Experiment report: {', '.join(experiments)}",
        "",
        f"{len(ok)} cells ok, {len(errors)} failed to run; total run time "
        f"{wall / 60:.1f} min (sum of cell wall times). Each table cell is the mean over "
        "repeats, with [lowest-highest repeat] when there are several; latency is the Hello "
        "round trip p50 (ms), loss the Hello loss (%), samples the sensor sample loss (%), "
        "staleness the worst robot's p99 (ms); mission is the share of successful repeats "
        "(successes/repeats).",
        "",
    ]
    has_hello = any(r["hello_sent"] for r in ok)
    has_mission = any(r["mission"] for r in ok)
    mixed = _mixed(ok)
    for network in sorted({r["network"] for r in ok}):
        for rmax in sorted({r["rmax_hz"] for r in ok if r["network"] == network}, key=_rate_key):
            sub = [r for r in ok if r["network"] == network and r["rmax_hz"] == rmax]
            configs = sorted({_series(r, mixed) for r in sub}, key=_series_order)
            depths = sorted({r["depth"] for r in sub}, key=_depth_order)
            lines += [f"## Rmax = {rmax} Hz, network {network}", ""]
            head = "| DEPTH | " + " | ".join(series_label(c) for c in configs) + " |"
            lines += [head, "|---|" + "---|" * len(configs)]
            for depth in depths:
                cells = []
                for config in configs:
                    g = groups.get((network, rmax, depth, config))
                    if not g:
                        cells.append("")
                        continue
                    parts = []
                    if has_hello:
                        parts.append(
                            f"{_ranged(g, 'latency_ms_p50')} ms, {_ranged(g, 'loss_pct', 2)} %"
                        )
                    parts.append(f"samples {_ranged(g, 'sample_loss_pct', 2)} % lost")
                    if any(r.get("staleness_ms_p99") for r in g):
                        parts.append(f"staleness {_ranged(g, 'staleness_ms_p99')} ms")
                    if has_mission:
                        wins = sum(r.get("mission") == "success" for r in g)
                        parts.append(f"mission {_fmt(_success(g))} % ({wins}/{len(g)})")
                    rate = _mean("rate_hz")(g)
                    parts.append(f"R {_fmt(rate)} D {g[0]['qos_depth']}")
                    if any(r.get("cpu_s_ceddp") for r in g):
                        parts.append(
                            f"CPU CEDDP {_ranged(g, 'cpu_s_ceddp')} s, "
                            f"robots {_ranged(g, 'cpu_s_robots')} s"
                        )
                    cells.append("<br>".join(parts))
                lines.append(f"| {_depth_label(depth)} | " + " | ".join(cells) + " |")
            lines.append("")
    problems = consistency(rows)
    lines += [
        "## Consistency",
        "",
        "Every ok row reconciles (every robot's final counters arrived, produced = sent + "
        "held back + write failures, sent = received + lost, Hello sent = received + lost, "
        "every robot's downlink reconciled where recorded)."
        if not problems
        else "\n".join(f"- {p}" for p in problems),
        "",
    ]
    if errors:
        lines += ["## Cells that failed to run", ""]
        lines += [
            f"- Rmax {r['rmax_hz']} depth {r['depth']} {r['config']} {r['network']} "
            f"repeat {r['repeat']}{'' if r['middleware'] == 'arpz' else ' ' + r['middleware']}: "
            f"{r['error']}"
            for r in errors
        ]
        lines.append("")
    combined = [p for p in figures if "_r" not in p.stem.removeprefix("experiment_")]
    if combined:
        lines += ["## Figures", ""]
        for path in combined:
            rel = path.relative_to(base) if path.is_relative_to(base) else path
            lines += [f"![{path.stem}]({rel.as_posix()})", ""]
    return "\n".join(lines)


def write_report(
    source: Path, *, figures: Path | None = None, out: Path | None = None
) -> list[Path]:
    """Rebuild REPORT.md and the figures from ``source`` (a results directory or a results.csv
    file, e.g. a committed one) into ``out`` (default: the CSV's directory; figures in
    ``out/figures`` unless ``figures`` says otherwise). Returns the paths written (REPORT.md
    first)."""
    results = source if source.suffix == ".csv" else source / "results.csv"
    directory = out or results.parent
    directory.mkdir(parents=True, exist_ok=True)
    try:
        rows = read_rows(results)
    except (OSError, KeyError, ValueError) as exc:
        raise ReportError(f"{results}: cannot read: {exc}") from None
    if not rows:
        raise ReportError(f"{results}: no results (run the experiment first)")
    ok = [r for r in rows if r["status"] == "ok"]
    written = write_figures(ok, figures or directory / "figures") if ok else []
    report = directory / "REPORT.md"
    report.write_text(markdown(rows, written, directory), encoding="utf-8")
    return [report, *written]
