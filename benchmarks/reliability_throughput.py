"""Throughput of arpz RELIABLE KEEP_ALL vs raw Zenoh vs zenoh.ext Advanced pub/sub, in one run.

Each measurement is one publisher process and one subscriber process through one router process
(``python -m arpz.perf``) on loopback; rounds are interleaved so that load from other programs
hits all transports alike, and the median round is reported. Targets (issue 3): arpz >= 0.6x raw
Zenoh and >= 1.0x Advanced.

arpz is measured three ways: with the default profile, whose adaptive write batching
(``batch_max_samples = 64``, as Cyclone DDS's WriteBatch) amortises the per-message cost of Python
and Zenoh when a topic is written faster than ``batch_max_delay_s``, and whose reader hands every
message to its worker thread before the callback runs; with ``--inline`` (``Reader(...,
inline_delivery=True)``), where the recording callback runs on Zenoh's thread as it does for the
raw and Advanced subscribers; and unbatched (``--batch 1``: every sample its own Zenoh message).

    python benchmarks/reliability_throughput.py --rounds 5
"""

from __future__ import annotations

import argparse
import statistics
from collections.abc import Callable
from functools import partial

from arpz.perf.harness import perf_router, pubsub
from arpz.tools.launch import free_port

#: progress lines, printed as they come
SAY = partial(print, flush=True)

#: (label, --transport, extra perf flags)
RUNS: tuple[tuple[str, str, tuple[str, ...]], ...] = (
    ("zenoh", "zenoh", ()),
    ("advanced", "advanced", ()),
    ("arpz", "arpz", ()),
    ("arpz inline", "arpz", ("--inline",)),
    ("arpz unbatched", "arpz", ("--batch", "1")),
)


def ratios(values: dict[str, float], label: str) -> str:
    return f"{values[label] / values['zenoh']:.2f}x | {values[label] / values['advanced']:.2f}x"


def measure(
    sizes: dict[int, int],
    rounds: int,
    runs: tuple[tuple[str, str, tuple[str, ...]], ...] = RUNS,
    log: Callable[[str], object] = SAY,
) -> tuple[dict[tuple[int, str], list[float]], dict[tuple[int, str], list[float]]]:
    """Per (payload size, label), one figure a round: msg/s (0 when a run lost samples) and
    CPU us a sample (publisher + subscriber). ``sizes``: payload bytes -> samples a run. Rounds
    run every label in turn, so a round's figures share a window of the host."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    results: dict[tuple[int, str], list[float]] = {}
    cpu: dict[tuple[int, str], list[float]] = {}
    with perf_router(endpoint):
        for size, count in sizes.items():
            for round_ in range(rounds):
                for label, transport, extra in runs:
                    pub, report = pubsub(
                        transport=transport,
                        pub_connect=endpoint,
                        sub_connect=endpoint,
                        count=count,
                        size=size,
                        extra=extra,
                    )
                    complete = report["received"] == count
                    rate = report["throughput_msg_s"] if complete else 0.0
                    results.setdefault((size, label), []).append(rate)
                    # CPU per sample, publisher + subscriber processes: stable on a shared host
                    per_msg = pub["cpu_us_per_msg"] + report["cpu_us_per_msg"]
                    cpu.setdefault((size, label), []).append(per_msg)
                    log(
                        f"  round {round_ + 1}/{rounds} {size:5d} B {label:13s} "
                        f"{rate:10.0f} msg/s  received {report['received']}"
                    )
    return results, cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--count", type=int, default=200_000, help="samples per run (24 B)")
    ap.add_argument("--count-kib", type=int, default=200_000, help="samples per run (1 KiB)")
    args = ap.parse_args()
    results, cpu = measure({24: args.count, 1024: args.count_kib}, args.rounds)
    print()
    print("Throughput, msg/s (median of the rounds), and arpz / raw Zenoh, arpz / Advanced:")
    table(results, "{:.0f}")
    print()
    print("CPU per sample (publisher + subscriber processes, all their threads), us:")
    table(cpu, "{:.1f}")


def table(values: dict[tuple[int, str], list[float]], fmt: str) -> None:
    labels = [label for label, _, _ in RUNS]
    arpz = [label for label in labels if label.startswith("arpz")]
    head = ["payload", "raw Zenoh", "Advanced", *arpz]
    head += [f"{label} / {base}" for label in arpz for base in ("raw", "Advanced")]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for size in (24, 1024):
        med = {label: statistics.median(values[(size, label)]) for label in labels}
        row = [f"{size} B", *(fmt.format(med[label]) for label in labels)]
        row += [ratios(med, label) for label in arpz]
        print("| " + " | ".join(row) + " |")


if __name__ == "__main__":
    main()
