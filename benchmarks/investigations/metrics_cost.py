"""What the CEDDP's reporting costs a series: the dashboard's metric flush and the percentiles.

Every ``flush_period_s`` (5 s) the Rerun dashboard sends each metric series' pending rows as one
column chunk; a fleet of 25 robots has about 2 400 series (9 metrics x 9 topics + 14 per robot).
Timed here, in one run, on the same series: ``Dashboard._flush_metrics`` (Arrow arrays built once,
a zero-copy slice a series) against what it did before, Rerun's own column builders a series
(``rr.TimeColumn`` and ``rr.Scalars.columns``), each into its own ``.rrd``.

The summary computes p50 and p99 of every topic's latency and staleness reservoirs every
``summary_period_s``: ``arpz.core.percentiles.percentiles`` (a sort and interpolation by hand)
against ``numpy.percentile``, on reservoirs of a slow topic (45 values), a list's bound (2 048) and
a full
reservoir (20 000).

The summary file is rewritten every ``summary_period_s``: ``write_json_atomically`` (msgspec's
encoder and formatter) against ``json.dumps(indent=2)``, whose indent sends the standard library
to its pure-Python encoder, on a summary shaped as a fleet's (``--robots``, 8 topics each).

    python benchmarks/investigations/metrics_cost.py [--series 2400] [--rows 10] [--rounds 3]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import rerun as rr

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from arpz.ceddp.dashboard import Dashboard
from arpz.ceddp.server import write_json_atomically
from arpz.core.frames import TIMELINE
from arpz.core.percentiles import percentiles

T0_S = 1_700_000_000.0

#: entity path -> (times in s, values): a dashboard's pending rows
Rows = dict[str, tuple[list[float], list[float]]]


def rows(series: int, per_series: int) -> Rows:
    rng = np.random.default_rng(1)
    return {
        f"/metrics/m{k % 9}/robot{k // 90}/topic{k % 90 // 9}": (
            [T0_S + 0.5 * i for i in range(per_series)],
            rng.random(per_series).tolist(),
        )
        for k in range(series)
    }


def flush_arpz(folder: Path, pending: Rows) -> float:
    """Seconds ``Dashboard._flush_metrics`` takes for these rows."""
    dashboard = Dashboard(folder / "arpz.rrd", flush_period_s=3600)
    for path, (times, values) in pending.items():
        for t_s, value in zip(times, values, strict=True):
            dashboard._add(path, t_s, value)
    start = time.perf_counter()
    dashboard._flush_metrics()
    elapsed = time.perf_counter() - start
    dashboard.close()
    return elapsed


def flush_rerun_builders(
    folder: Path, pending: dict[str, tuple[list[float], list[float]]]
) -> float:
    """Seconds the flush took before (f2f454c): Rerun's column builders, one series at a time."""
    rec = rr.RecordingStream("baseline")
    rec.set_sinks(rr.FileSink(str(folder / "baseline.rrd")))
    start = time.perf_counter()
    for path, (times, values) in pending.items():
        stamps = (np.asarray(times) * 1e9).astype("datetime64[ns]")
        rec.send_columns(
            path,
            indexes=[rr.TimeColumn(TIMELINE, timestamp=stamps)],
            columns=rr.Scalars.columns(scalars=np.asarray(values, dtype=np.float64)),
        )
    elapsed = time.perf_counter() - start
    rec.flush()
    rec.disconnect()
    return elapsed


def per_call_us(fn: Callable[[], object], seconds: float = 0.5) -> float:
    calls, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        fn()
        calls += 1
    return (time.perf_counter() - start) / calls * 1e6


def fleet_summary(robots: int, topics: int = 8) -> dict[str, object]:
    """A summary shaped as the CEDDP's: per robot its counters and, per topic, about 30 figures
    (a 25-robot one is about 270 KB of indented JSON, as a real one)."""
    rng = np.random.default_rng(3)

    def figures(n: int, prefix: str) -> dict[str, object]:
        return {f"{prefix}_{i}": round(float(rng.random() * 1000), 3) for i in range(n)}

    return {
        "fleet": "bench",
        "robots": {
            f"robot{r}": {
                **figures(30, "robot"),
                "topics": {f"topic{t}": figures(30, "topic") for t in range(topics)},
                "incarnations": {"0123456789abcdef": {"sent": 100, "reconciled": True}},
            }
            for r in range(robots)
        },
    }


def write_dumps(path: Path, doc: dict[str, object]) -> None:
    """How the summary was written before."""
    path.write_text(json.dumps(doc, indent=2), encoding="utf-8")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--series", type=int, default=2400)
    ap.add_argument("--rows", type=int, default=10, help="rows a series holds at a flush")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--robots", type=int, default=25, help="robots in the summary file")
    args = ap.parse_args()
    pending = rows(args.series, args.rows)
    ours, theirs = [], []
    for round_ in range(1, args.rounds + 1):
        with tempfile.TemporaryDirectory() as tmp:
            ours.append(flush_arpz(Path(tmp), pending))
            theirs.append(flush_rerun_builders(Path(tmp), pending))
        print(
            f"round {round_}/{args.rounds}: arpz {ours[-1] * 1e3:.0f} ms, "
            f"Rerun builders {theirs[-1] * 1e3:.0f} ms",
            file=sys.stderr,
        )
    a, b = statistics.median(ours), statistics.median(theirs)
    print(f"dashboard flush, {args.series} series x {args.rows} rows, median of {args.rounds}:")
    for name, total in (("Rerun's column builders", b), ("arpz, slices of one array", a)):
        print(f"  {name:<25} : {total / args.series * 1e6:8.1f} us a series ({total * 1e3:.0f} ms)")
    print(f"  {'ratio arpz / builders':<25} : {a / b:8.2f}x")
    print("percentiles (p50, p99) of one array:")
    rng = np.random.default_rng(2)
    for n in (45, 2048, 20_000):
        values = rng.random(n)
        mine = per_call_us(lambda v=values: percentiles(v, (50.0, 99.0)))
        numpy = per_call_us(lambda v=values: np.percentile(v, (50.0, 99.0)))
        assert np.allclose(percentiles(values, (50.0, 99.0)), np.percentile(values, (50.0, 99.0)))
        print(
            f"  {n:>6} values: arpz {mine:7.1f} us, numpy.percentile {numpy:7.1f} us, "
            f"ratio {mine / numpy:.2f}x"
        )
    doc = fleet_summary(args.robots)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "summary.json"
        fast = per_call_us(lambda: write_json_atomically(path, doc), seconds=1.0)
        size = path.stat().st_size
        assert json.loads(path.read_text(encoding="utf-8")) == doc
        slow = per_call_us(lambda: write_dumps(path, doc), seconds=1.0)
    print(f"summary file, {args.robots} robots ({size / 1e3:.0f} KB):")
    print(f"  json.dumps(indent=2)      : {slow / 1e3:8.1f} ms")
    print(f"  write_json_atomically     : {fast / 1e3:8.1f} ms")
    print(f"  {'ratio':<25} : {fast / slow:8.2f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
