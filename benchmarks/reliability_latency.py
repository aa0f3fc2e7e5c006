"""Round-trip latency at 1 kHz: arpz (RELIABLE KEEP_ALL) vs raw Zenoh vs Advanced, in one run.

``ping`` and ``pong`` processes (``python -m arpz.perf``) through one router process, express
publishers for all; rounds interleaved, medians of the per-round p50/p99 reported. Target
(issue 3): arpz p50 and p99 at most 1.3x raw Zenoh.

    python benchmarks/reliability_latency.py --rounds 3 --count 3000
"""

from __future__ import annotations

import argparse
import statistics

from arpz.perf.harness import free_port, perf_router, pingpong

#: (label, transport, extra flags); "arpz-inline" delivers on the transport thread
VARIANTS = (
    ("zenoh", "zenoh", ()),
    ("advanced", "advanced", ()),
    ("arpz", "arpz", ()),
    ("arpz-inline", "arpz", ("--inline",)),
)
TRANSPORTS = tuple(label for label, _, _ in VARIANTS)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--count", type=int, default=3000)
    ap.add_argument("--rate", type=float, default=1000.0)
    args = ap.parse_args()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    p50: dict[str, list[float]] = {t: [] for t in TRANSPORTS}
    p99: dict[str, list[float]] = {t: [] for t in TRANSPORTS}
    with perf_router(endpoint):
        for _ in range(args.rounds):
            for transport, name, flags in VARIANTS:
                report = pingpong(
                    transport=name,
                    connect=endpoint,
                    count=args.count,
                    rate_hz=args.rate,
                    extra=["--express", *flags],
                )
                lat = report["latency_us"]
                p50[transport].append(lat["p50"])
                p99[transport].append(lat["p99"])
                print(
                    f"  {transport:9s} p50 {lat['p50']:8.1f} us  p99 {lat['p99']:8.1f} us  "
                    f"received {report['received']}/{report['sent']}"
                )
    med50 = {t: statistics.median(v) for t, v in p50.items()}
    med99 = {t: statistics.median(v) for t, v in p99.items()}
    print()
    print("| transport | RTT p50 us | RTT p99 us | p50 / raw | p99 / raw |")
    print("|---|---|---|---|---|")
    for t in TRANSPORTS:
        print(
            f"| {t} | {med50[t]:.0f} | {med99[t]:.0f} | {med50[t] / med50['zenoh']:.2f}x "
            f"| {med99[t] / med99['zenoh']:.2f}x |"
        )


if __name__ == "__main__":
    main()
