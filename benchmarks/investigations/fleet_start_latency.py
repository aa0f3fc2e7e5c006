"""Which robots of a fleet run started late, and why: each robot's latency p50 in the first
seconds of the load against after them, beside its first clock estimate, read back from the
CEDDP's ``.rrd`` (the dashboard's ``/metrics`` series).

How stop 39 of issue 17 found that the worst robots' p99 at 50 robots was their first clock
estimate: 50 robots starting at once gave some a first exchange with a round trip of 23-55 ms,
whose offset (off by up to half of it, on one host where the true offset is 0) the CEDDP took
out of their latencies until a better estimate came:

    python -m arpz.perf fleet --robots 50 --topics 8 --rate 100 --processes 4 --duration 60 \\
        --workdir /tmp/fw1
    python benchmarks/investigations/fleet_start_latency.py /tmp/fw1/ceddp0.rrd [--first-s 2]
        [--top 10]

A robot whose p50 was high at first and normal afterwards, with a first clock offset of about
that much, was mis-corrected, not late.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from arpz.core.frames import TIMELINE  # noqa: E402


def series(rrd: Path, names: tuple[str, ...]) -> dict[str, list[tuple[int, float]]]:
    """entity path -> [(stamp_ns, value)] of the ``/metrics/NAME/...`` series named."""
    from rerun.chunk import RrdReader

    out: dict[str, list[tuple[int, float]]] = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a CEDDP killed hard leaves no footer
        chunks = RrdReader(str(rrd)).stream().filter(content="/metrics/**", is_static=False)
        for chunk in chunks.to_chunks():
            path = str(chunk.entity_path)
            if path.split("/")[2] not in names:
                continue
            batch = chunk.to_record_batch()
            stamps = batch.column(TIMELINE).cast("int64").to_pylist()
            values = batch.column("Scalars:scalars").to_pylist()
            out.setdefault(path, []).extend(
                (stamp, value[0]) for stamp, value in zip(stamps, values, strict=True)
            )
    return {path: sorted(rows) for path, rows in out.items()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("rrd", type=Path, help="a CEDDP's .rrd (perf fleet --workdir: ceddpK.rrd)")
    ap.add_argument("--first-s", type=float, default=2.0, help="the start's length (2 s)")
    ap.add_argument("--top", type=int, default=10, help="robots to print (10)")
    args = ap.parse_args()
    if not args.rrd.is_file():
        print(f"fleet_start_latency: no such file: {args.rrd}", file=sys.stderr)
        return 2
    try:
        rows = series(args.rrd, ("latency_ms_p50", "clock_offset_ms", "clock_delay_ms"))
    except RuntimeError as exc:  # rerun's reader: not an .rrd, or cut short
        print(f"fleet_start_latency: cannot read {args.rrd}: {exc}", file=sys.stderr)
        return 2
    p50 = {p.split("/")[3]: v for p, v in rows.items() if p.startswith("/metrics/latency_ms_p50/")}
    if not p50:
        print(f"fleet_start_latency: no latency series in {args.rrd}", file=sys.stderr)
        return 1
    t0 = min(v[0][0] for v in p50.values() if v)
    first_ns = args.first_s * 1e9
    table = []
    for robot in sorted(p50):
        # every topic of the robot: the worst interval p50 at the start and after it
        topics = [v for p, v in rows.items() if p.startswith(f"/metrics/latency_ms_p50/{robot}/")]
        start = [x for v in topics for t, x in v if t - t0 < first_ns]
        later = [x for v in topics for t, x in v if t - t0 >= first_ns]
        offset = rows.get(f"/metrics/clock_offset_ms/{robot}") or [(0, float("nan"))]
        delay = rows.get(f"/metrics/clock_delay_ms/{robot}") or [(0, float("nan"))]
        table.append(
            (max(start, default=0.0), robot, max(later, default=0.0), offset[0][1], delay[0][1])
        )
    table.sort(reverse=True)
    print(
        f"{'robot':>10} {'p50 first ' + format(args.first_s, 'g') + ' s':>14} "
        f"{'p50 after':>10} {'1st clock offset':>17} {'its round trip':>15}"
    )
    for start_ms, robot, later_ms, offset_ms, delay_ms in table[: args.top]:
        print(
            f"{robot:>10} {start_ms:11.1f} ms {later_ms:7.1f} ms {offset_ms:14.2f} ms "
            f"{delay_ms:12.2f} ms"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
