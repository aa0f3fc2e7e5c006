"""The entries of ``python -m benchmarks``: each measures arpz and its baseline in the same run
through the benchmark script it names (so the suite and the script measure the same thing),
and returns its ratios. Cheapest first. Their references are in benchmarks/RESULTS.md.

``quick``: fewer samples and rounds, for a smoke test; the same ratios.
"""

from __future__ import annotations

import random
import statistics
import sys

from benchmarks.measurement import Entry, Measurement, median_ratio


def LOG(line: str) -> None:
    """The scripts' progress lines: to stderr as it is now (the suite captures it unless
    --verbose)."""
    print(line, file=sys.stderr, flush=True)


def optimiser(quick: bool) -> Measurement:
    from benchmarks import optimiser_solve_time as bench

    settings = bench.SETTINGS[:1] if quick else bench.SETTINGS
    rmax = (100.0, 1000.0) if quick else bench.RMAX_HZ
    rows = bench.measure(200 if quick else 1000, 5 if quick else 15, settings, rmax, LOG)
    ratios = [cvxpy_s / closed_s for *_, closed_s, cvxpy_s, _ in rows]
    closed_us = statistics.median(row[4] for row in rows) * 1e6
    cvxpy_ms = statistics.median(row[5] for row in rows) * 1e3
    return Measurement(
        {"CVXPY / closed form, solve time": statistics.median(ratios)},
        [f"closed form {closed_us:.1f} us a solve, CVXPY {cvxpy_ms:.2f} ms ({len(rows)} settings)"],
    )


def write_cost(quick: bool) -> Measurement:
    from benchmarks import reliability_write_cost as bench

    rounds = [bench.measure(10_000 if quick else 50_000, log=LOG) for _ in range(1 if quick else 3)]
    cpu = {
        label: [r[1] for rows in rounds for r in rows if r[0] == label] for label, *_ in rounds[0]
    }
    bare, batched, unbatched = (cpu[label] for label, _, _ in bench.CASES)
    return Measurement(
        {
            "Writer.write / bare put, CPU a call": median_ratio(batched, bare),
            "unbatched Writer.write / bare put": median_ratio(unbatched, bare),
        },
        [
            f"main-thread CPU a call (24 B): bare put {statistics.median(bare):.2f} us, "
            f"Writer.write {statistics.median(batched):.2f} us, unbatched "
            f"{statistics.median(unbatched):.2f} us"
        ],
    )


def throughput(quick: bool) -> Measurement:
    from benchmarks import reliability_throughput as bench

    runs = tuple(run for run in bench.RUNS if run[0] in ("zenoh", "advanced", "arpz"))
    count = 20_000 if quick else 100_000
    rates, cpu = bench.measure({24: count, 1024: count // 2}, 1 if quick else 5, runs, LOG)
    ratios = {}
    details = []
    for size, name in ((24, "24 B"), (1024, "1 KiB")):
        for base, base_name in (("zenoh", "raw Zenoh"), ("advanced", "Advanced")):
            ours, theirs = rates[(size, "arpz")], rates[(size, base)]
            ratios[f"arpz / {base_name}, {name}"] = median_ratio(ours, theirs)
        ratios[f"CPU a sample, arpz / raw Zenoh, {name}"] = median_ratio(
            cpu[(size, "arpz")], cpu[(size, "zenoh")]
        )
        med = {label: statistics.median(rates[(size, label)]) for label, _, _ in runs}
        details.append(
            f"{name}: msg/s raw Zenoh {med['zenoh']:,.0f}, Advanced {med['advanced']:,.0f}, "
            f"arpz {med['arpz']:,.0f}"
        )
    return Measurement(ratios, details)


def latency(quick: bool) -> Measurement:
    from benchmarks import reliability_latency as bench

    variants = tuple(v for v in bench.VARIANTS if v[0] in ("zenoh", "advanced", "arpz"))
    p50, p99, _ = bench.measure(
        1 if quick else 5, 500 if quick else 1500, variants=variants, log=LOG
    )
    ratios = {}
    for pct, values in (("p50", p50), ("p99", p99)):
        for base, base_name in (("zenoh", "raw Zenoh"), ("advanced", "Advanced")):
            ratios[f"{pct}, arpz / {base_name}"] = median_ratio(values["arpz"], values[base])
    details = [
        "round trip at 1 kHz, us (p50 / p99): "
        + ", ".join(
            f"{label} {statistics.median(p50[label]):.0f} / {statistics.median(p99[label]):.0f}"
            for label, _, _ in variants
        )
    ]
    return Measurement(ratios, details)


LOSS_PCT = 10.0


def lossy(quick: bool) -> Measurement:
    from benchmarks import reliability_lossy as bench

    count = 1000 if quick else 3000
    # raw Zenoh recovers nothing: 2 s without a sample ends it; Advanced's recoveries took
    # seconds at this loss
    idle_s = {"arpz": 6.0, "zenoh": 2.0, "advanced": 6.0}
    reports = {t: bench.run(LOSS_PCT, t, count, 1000.0, idle_s[t]) for t in idle_s}
    delivered = {t: r["received"] / count for t, r in reports.items()}
    p99_ms = {
        t: (r["latency_us"] or {}).get("p99", float("nan")) / 1000 for t, r in reports.items()
    }
    return Measurement(
        {
            "delivered, arpz / raw Zenoh": delivered["arpz"] / delivered["zenoh"],
            "delivered, arpz / Advanced": delivered["arpz"] / delivered["advanced"],
            "p99, arpz / raw Zenoh": p99_ms["arpz"] / p99_ms["zenoh"],
        },
        [
            f"1 kHz, {count} samples, {LOSS_PCT:g} % loss each way: "
            + "; ".join(
                f"{t} delivered {100 * delivered[t]:.1f} %, p99 {p99_ms[t]:.1f} ms, longest stall "
                f"{r['longest_stall_ms']:.0f} ms, reported lost {r['lost']}, vanished "
                f"{r['unaccounted']}"
                for t, r in reports.items()
            )
        ],
    )


def ceddp_ingest(quick: bool) -> Measurement:
    from benchmarks import ceddp_ingest as bench

    paths = ["channel", "channel-unbatched"]
    total = 40_000 if quick else 200_000
    raw, ours, cpu = bench.measure(total, 2, paths, 1 if quick else 3, log=LOG)
    return Measurement(
        {
            "channel / raw subscriber": median_ratio(ours["channel"], raw),
            "one sample a message / raw subscriber": median_ratio(ours["channel-unbatched"], raw),
            "CPU a sample, channel / raw subscriber": median_ratio(cpu["channel"], cpu["raw"]),
        },
        [
            f"{total} samples, samples/s: raw subscriber {statistics.median(raw):,.0f}, "
            f"CEDDP through the channel {statistics.median(ours['channel']):,.0f}, one sample a "
            f"message {statistics.median(ours['channel-unbatched']):,.0f}; CPU a sample, us: "
            f"raw {statistics.median(cpu['raw']):.2f}, channel "
            f"{statistics.median(cpu['channel']):.2f}"
        ],
    )


def large_messages(quick: bool) -> Measurement:
    from arpz.core.endpoints import frame_fragment_bytes
    from benchmarks import large_messages as bench

    rng = random.Random(7)
    size = 921_600
    flat = [rng.randbytes(size) for _ in range(30 if quick else 100)]
    fragment = frame_fragment_bytes(["tcp/127.0.0.1:7447"])  # what a robot on TCP cuts
    goodput: dict[str, list[float]] = {"zenoh": [], "arpz": []}
    for _ in range(1 if quick else 5):
        base = bench.run_cell(bench.Cell("tcp", 0.0, "zenoh", 0.0), flat, seed=0)
        ours = bench.run_cell(bench.Cell("tcp", 0.0, "arpz", 0.0, fragment), flat, seed=0)
        goodput["zenoh"].append(base.goodput_mbs)
        goodput["arpz"].append(ours.goodput_mbs)
    frames = [rng.randbytes(size) for _ in range(10 if quick else 30)]
    udp = {
        t: bench.run_cell(bench.Cell("udp", 1.0, t, 10.0), frames, seed=11)
        for t in ("arpz", "zenoh")
    }
    return Measurement(
        {
            "TCP flat out, arpz (60 KiB fragments) / raw Zenoh": median_ratio(
                goodput["arpz"], goodput["zenoh"]
            ),
            "UDP 1 % loss, frames delivered whole, arpz / sent": udp["arpz"].intact / len(frames),
        },
        [
            f"TCP flat out, {len(flat)} frames of {size} B, MB/s: raw Zenoh "
            f"{statistics.median(goodput['zenoh']):.0f}, "
            f"arpz {statistics.median(goodput['arpz']):.0f}",
            f"UDP at 1 % loss per 1 500-byte frame, 10 Hz: arpz {udp['arpz'].intact} of "
            f"{len(frames)} whole, raw Zenoh {udp['zenoh'].intact}",
        ],
    )


def fleet(quick: bool) -> Measurement:
    from benchmarks import fleet_raw as bench

    robots, duration, rounds = (4, 3.0, 1) if quick else (10, 8.0, 2)
    pairs = bench.measure(robots, 8, 100.0, 2, duration, rounds, log=LOG)
    ratios = bench.ratios(pairs)
    point, raw = pairs[-1]
    return Measurement(
        {
            "p99 median robot, arpz / raw Zenoh": ratios["p99, median robot"],
            "p99 worst robot, arpz / raw Zenoh": ratios["p99, worst robot"],
            "CPU a sample, CEDDP / raw subscriber": ratios["CPU a sample"],
            "delivered, arpz / raw Zenoh": ratios["delivered"],
        },
        [
            f"{robots} robots x 8 topics x 100 Hz, 2 worker processes, {duration:g} s: arpz "
            f"delivered {point.delivered_ratio:.3f} of offered, lost {point.lost}, p99 median "
            f"robot {point.latency_ms_p99_median_robot:.2f} ms, worst {point.latency_ms_p99:.2f} "
            f"ms, CEDDP {point.ceddp_cpu_us_per_sample} us a sample; raw Zenoh delivered "
            f"{raw.delivered_ratio:.3f}, p99 {raw.latency_ms_p99_median_robot:.2f} / "
            f"{raw.latency_ms_p99:.2f} ms, subscriber {raw.cpu_us_per_sample:.1f} us a sample"
        ],
    )


ENTRIES: tuple[Entry, ...] = (
    Entry(
        "optimiser",
        "QoS balancing: the closed form's solve time against CVXPY's (the paper's), in process",
        {"CVXPY / closed form, solve time": "higher"},
        optimiser,
        5,
    ),
    Entry(
        "write_cost",
        "CPU of one publish on the calling thread: Writer.write against a bare Zenoh put",
        {
            "Writer.write / bare put, CPU a call": "lower",
            "unbatched Writer.write / bare put": "lower",
        },
        write_cost,
        10,
    ),
    Entry(
        "throughput",
        "RELIABLE KEEP_ALL flat out, pub -> router -> sub, against raw Zenoh and Advanced",
        {
            "arpz / raw Zenoh, 24 B": "higher",
            "arpz / Advanced, 24 B": "higher",
            "arpz / raw Zenoh, 1 KiB": "higher",
            "arpz / Advanced, 1 KiB": "higher",
            "CPU a sample, arpz / raw Zenoh, 24 B": "lower",
            "CPU a sample, arpz / raw Zenoh, 1 KiB": "lower",
        },
        throughput,
        50,
    ),
    Entry(
        "latency",
        "round trip at 1 kHz through a router, express, against raw Zenoh and Advanced",
        {
            "p50, arpz / raw Zenoh": "lower",
            "p50, arpz / Advanced": "lower",
            "p99, arpz / raw Zenoh": "lower",
            "p99, arpz / Advanced": "lower",
        },
        latency,
        45,
    ),
    Entry(
        "lossy",
        f"1 kHz over a link losing {LOSS_PCT:g} % each way (arpz.netem): arpz, raw Zenoh, Advanced",
        {
            "delivered, arpz / raw Zenoh": "higher",
            "delivered, arpz / Advanced": "higher",
            "p99, arpz / raw Zenoh": "lower",
        },
        lossy,
        32,
    ),
    Entry(
        "ceddp_ingest",
        "the real CEDDP's ingest through its fleet Reader against a raw counting subscriber",
        {
            "channel / raw subscriber": "higher",
            "one sample a message / raw subscriber": "higher",
            "CPU a sample, channel / raw subscriber": "lower",
        },
        ceddp_ingest,
        25,
    ),
    Entry(
        "large_messages",
        "921 600-byte frames: goodput over TCP against raw Zenoh, whole frames over lossy UDP",
        {
            "TCP flat out, arpz (60 KiB fragments) / raw Zenoh": "higher",
            "UDP 1 % loss, frames delivered whole, arpz / sent": "higher",
        },
        large_messages,
        25,
    ),
    Entry(
        "fleet",
        "10 real robots x 8 topics x 100 Hz into a real CEDDP against the same fleet on raw Zenoh",
        {
            "p99 median robot, arpz / raw Zenoh": "lower",
            "p99 worst robot, arpz / raw Zenoh": "lower",
            "CPU a sample, CEDDP / raw subscriber": "lower",
            "delivered, arpz / raw Zenoh": "higher",
        },
        fleet,
        50,
    ),
)
