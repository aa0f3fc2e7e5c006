"""1 kHz over a lossy link: arpz RELIABLE KEEP_ALL vs Advanced pub/sub vs raw Zenoh, in one run.

The publisher reaches the router over ``udp/`` through ``python -m arpz.netem`` (random loss
each way, after a clean start so the session opens); the subscriber is on TCP. Reported per loss
rate: delivered %, losses the transport reported, samples that vanished unreported, p99 latency
(source stamp to delivery) and the longest stall between two deliveries. Target (issue 3): arpz
delivers 100 % with a longest stall of a few round trips plus the NACK delay.

    python benchmarks/reliability_lossy.py --loss 10 30 --count 5000 [--transports arpz]
"""

from __future__ import annotations

import argparse
from typing import Any

from arpz.perf.harness import lossy_setup, pubsub

TRANSPORTS = ("arpz", "advanced", "zenoh")


def run(
    loss_pct: float, transport: str, count: int, rate_hz: float, idle_timeout_s: float = 15.0
) -> dict[str, Any]:
    """One publisher through a fresh lossy link, one subscriber on TCP; the subscriber's
    report. ``idle_timeout_s``: how long the subscriber waits for a sample after the last one
    once the end is known (Advanced's recoveries took up to 5.7 s at 10-30 % loss)."""
    with lossy_setup(loss_pct, 3.0) as (lossy, tcp):
        _, report = pubsub(
            transport=transport,
            pub_connect=lossy,
            sub_connect=tcp,
            count=count,
            rate_hz=rate_hz,
            extra=["--warmup", "2.5", "--idle-timeout", str(idle_timeout_s)],
            timeout_s=300,
        )
    return report


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--loss", type=float, nargs="+", default=[10.0, 30.0])
    ap.add_argument("--count", type=int, default=5000)
    ap.add_argument("--rate", type=float, default=1000.0)
    ap.add_argument(
        "--transports",
        default=",".join(TRANSPORTS),
        help="comma-separated subset of %(default)s (arpz alone for an A/B of two arpz commits)",
    )
    args = ap.parse_args()
    transports = [t for t in args.transports.split(",") if t]
    unknown = sorted(set(transports) - set(TRANSPORTS))
    if unknown or not transports:
        ap.error(
            f"unknown or no transport(s) {', '.join(unknown)}; choose from {', '.join(TRANSPORTS)}"
        )
    rows = []
    for loss in args.loss:
        for transport in transports:
            r = run(loss, transport, args.count, args.rate)
            lat = r["latency_us"] or {"p50": float("nan"), "p99": float("nan")}
            row = (
                f"| {loss:.0f} % | {transport} | {100 * r['received'] / args.count:.1f} % "
                f"| {r['lost']} | {r['unaccounted']} | {lat['p50'] / 1000:.1f} "
                f"| {lat['p99'] / 1000:.1f} | {r['longest_stall_ms']:.0f} | {r['retransmissions']} "
                f"| {r['duplicates']} / {r['out_of_order']} |"
            )
            print(row, flush=True)
            rows.append(row)
    print()
    print(
        "| loss | transport | delivered | reported lost | vanished unreported | p50 ms | p99 ms "
        "| longest stall ms | retransmitted | dup / out of order |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
