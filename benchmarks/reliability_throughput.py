"""Throughput of arpz RELIABLE KEEP_ALL vs raw Zenoh vs zenoh.ext Advanced pub/sub, in one run.

Each measurement is one publisher process and one subscriber process through one router process
(``python -m arpz.perf``) on loopback; rounds are interleaved so that load from other programs
hits all transports alike, and the median round is reported. Targets (issue 3): arpz >= 0.6x raw
Zenoh and >= 1.0x Advanced.

    python benchmarks/reliability_throughput.py --rounds 3
"""

from __future__ import annotations

import argparse
import statistics

from arpz.perf.harness import free_port, perf_router, pubsub

TRANSPORTS = ("zenoh", "advanced", "arpz")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--count", type=int, default=100_000, help="samples per run (24 B)")
    ap.add_argument("--count-kib", type=int, default=50_000, help="samples per run (1 KiB)")
    args = ap.parse_args()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    results: dict[tuple[int, str], list[float]] = {}
    cpu: dict[tuple[int, str], list[float]] = {}
    with perf_router(endpoint):
        for size, count in ((24, args.count), (1024, args.count_kib)):
            for _ in range(args.rounds):
                for transport in TRANSPORTS:
                    pub, report = pubsub(
                        transport=transport,
                        pub_connect=endpoint,
                        sub_connect=endpoint,
                        count=count,
                        size=size,
                    )
                    complete = report["received"] == count
                    rate = report["throughput_msg_s"] if complete else 0.0
                    results.setdefault((size, transport), []).append(rate)
                    # CPU per sample, publisher + subscriber processes: stable on a shared host
                    per_msg = pub["cpu_us_per_msg"] + report["cpu_us_per_msg"]
                    cpu.setdefault((size, transport), []).append(per_msg)
                    print(
                        f"  {size:5d} B {transport:9s} {rate:10.0f} msg/s  "
                        f"received {report['received']}"
                    )
    print()
    print(
        "| payload | raw Zenoh msg/s | Advanced msg/s | arpz msg/s | arpz / raw | arpz / Advanced |"
    )
    print("|---|---|---|---|---|---|")
    for size in (24, 1024):
        med = {t: statistics.median(results[(size, t)]) for t in TRANSPORTS}
        print(
            f"| {size} B | {med['zenoh']:.0f} | {med['advanced']:.0f} | {med['arpz']:.0f} "
            f"| {med['arpz'] / med['zenoh']:.2f}x | {med['arpz'] / med['advanced']:.2f}x |"
        )
    print()
    print("CPU per sample (publisher + subscriber processes, all their threads):")
    print("| payload | raw Zenoh us | Advanced us | arpz us | arpz / raw | arpz / Advanced |")
    print("|---|---|---|---|---|---|")
    for size in (24, 1024):
        c = {t: statistics.median(cpu[(size, t)]) for t in TRANSPORTS}
        print(
            f"| {size} B | {c['zenoh']:.1f} | {c['advanced']:.1f} | {c['arpz']:.1f} "
            f"| {c['arpz'] / c['zenoh']:.2f}x | {c['arpz'] / c['advanced']:.2f}x |"
        )


if __name__ == "__main__":
    main()
