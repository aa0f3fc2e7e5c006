"""Round-trip latency at 1 kHz: arpz (RELIABLE KEEP_ALL) vs raw Zenoh vs Advanced, in one run.

``ping`` and ``pong`` processes (``python -m arpz.perf``) through one router process, express
publishers for all; rounds interleaved, medians of the per-round p50/p99 reported. Target
(issue 3): arpz p50 and p99 at most 1.3x raw Zenoh.

    python benchmarks/reliability_latency.py --rounds 5 --count 3000 \
        --png docs/figures/reliability_latency.png

``--png`` draws every round trip of every round as one distribution per transport (CDF, log
scale), the picture behind the table.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from pathlib import Path

import numpy as np

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
    ap.add_argument("--png", type=Path, help="draw the round-trip distributions to this file")
    args = ap.parse_args()
    tmp = tempfile.TemporaryDirectory(prefix="arpz-latency-")
    workdir = Path(tmp.name)
    samples: dict[str, list[np.ndarray]] = {t: [] for t in TRANSPORTS}
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    p50: dict[str, list[float]] = {t: [] for t in TRANSPORTS}
    p99: dict[str, list[float]] = {t: [] for t in TRANSPORTS}
    with perf_router(endpoint):
        for round_no in range(args.rounds):
            for transport, name, flags in VARIANTS:
                out = workdir / f"{transport}-{round_no}.npy"
                report = pingpong(
                    transport=name,
                    connect=endpoint,
                    count=args.count,
                    rate_hz=args.rate,
                    extra=["--express", *flags, "--latency-out", str(out)],
                )
                samples[transport].append(np.load(out))
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

    tmp.cleanup()
    if args.png is not None:
        draw(samples, args.png, args.rate)
        print(f"\nwrote {args.png}")


def draw(samples: dict[str, list[np.ndarray]], png: Path, rate_hz: float) -> None:
    """Per transport, over every round trip of every round: the CDF, and the tail (the share
    slower than x, log scale), where p99 differences show."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter, ScalarFormatter

    fig, (body, tail) = plt.subplots(1, 2, figsize=(11, 4.2))
    for transport, rounds in samples.items():
        values = np.sort(np.concatenate(rounds))
        share = np.arange(1, len(values) + 1) / len(values)
        p50, p99 = np.percentile(values, [50, 99])
        label = f"{transport} (p50 {p50:.0f} us, p99 {p99:.0f} us)"
        body.plot(values, share, label=label)
        tail.plot(values, 1.0 - share + 1.0 / len(values), label=transport)
    for ax in (body, tail):
        ax.set_xscale("log")
        ax.set_xticks([150, 200, 300, 500, 1000, 2000, 5000])
        ax.xaxis.set_major_formatter(ScalarFormatter())
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("round trip (us)")
        ax.grid(True, which="both", alpha=0.3)
    body.set_ylabel("share of round trips")
    body.legend(loc="lower right", fontsize=8)
    tail.set_yscale("log")
    tail.set_ylabel("share slower than x")
    tail.axhline(0.01, color="grey", lw=0.8, ls="--")
    fig.suptitle(f"Round trip at {rate_hz:.0f} Hz through one router (24 B, express publishers)")
    fig.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
