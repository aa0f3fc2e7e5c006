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
from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np

from arpz.perf.harness import perf_router, pingpong
from arpz.tools.launch import free_port

#: progress lines, printed as they come
SAY = partial(print, flush=True)

#: (label, transport, extra flags); "arpz-inline" delivers on the transport thread
VARIANTS = (
    ("zenoh", "zenoh", ()),
    ("advanced", "advanced", ()),
    ("arpz", "arpz", ()),
    ("arpz-inline", "arpz", ("--inline",)),
)
TRANSPORTS = tuple(label for label, _, _ in VARIANTS)


def measure(
    rounds: int,
    count: int,
    rate_hz: float = 1000.0,
    variants: tuple[tuple[str, str, tuple[str, ...]], ...] = VARIANTS,
    keep_samples: bool = False,
    log: Callable[[str], object] = SAY,
) -> tuple[dict[str, list[float]], dict[str, list[float]], dict[str, list[np.ndarray]]]:
    """Per variant, each round's round-trip p50 and p99 (us), and with ``keep_samples`` every
    round trip of every round. Rounds run every variant in turn."""
    samples: dict[str, list[np.ndarray]] = {label: [] for label, _, _ in variants}
    p50: dict[str, list[float]] = {label: [] for label, _, _ in variants}
    p99: dict[str, list[float]] = {label: [] for label, _, _ in variants}
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with tempfile.TemporaryDirectory(prefix="arpz-latency-") as tmp, perf_router(endpoint):
        for round_no in range(rounds):
            for label, name, flags in variants:
                out = Path(tmp) / f"{label}-{round_no}.npy"
                keep = ["--latency-out", str(out)] if keep_samples else []
                report = pingpong(
                    transport=name,
                    connect=endpoint,
                    count=count,
                    rate_hz=rate_hz,
                    extra=["--express", *flags, *keep],
                )
                if keep_samples:
                    samples[label].append(np.load(out))
                lat = report["latency_us"]
                p50[label].append(lat["p50"])
                p99[label].append(lat["p99"])
                log(
                    f"  {label:11s} p50 {lat['p50']:8.1f} us  p99 {lat['p99']:8.1f} us  "
                    f"received {report['received']}/{report['sent']}"
                )
    return p50, p99, samples


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--count", type=int, default=3000)
    ap.add_argument("--rate", type=float, default=1000.0)
    ap.add_argument("--png", type=Path, help="draw the round-trip distributions to this file")
    args = ap.parse_args()
    p50, p99, samples = measure(args.rounds, args.count, args.rate, keep_samples=bool(args.png))
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
