"""CPU cost of one publish on the publishing thread: a plain Zenoh put vs arpz ``Writer.write``
(default, which batches writes, and unbatched), in one run.

A router process and a subscriber process (``python -m arpz.perf``: plain Zenoh for the bare put,
an arpz reader for the Writer, so acknowledgements flow) run on loopback; this process publishes
24 B samples as fast as it can and reads its main thread's CPU time (``time.thread_time``), which
counts the Python and Zenoh work of the call itself and not the other threads, and wall time.
This is the per-sample cost that bounds the publisher in benchmarks/reliability_throughput.py.

    python benchmarks/reliability_write_cost.py [--count 200000]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from functools import partial

from arpz.channel import HistoryPolicy, QosProfile, Writer
from arpz.core.transport import SessionSettings
from arpz.perf.harness import _perf, child, perf_router
from arpz.tools.launch import free_port
from arpz.transport.zenoh import ZenohTransport

#: progress lines, printed as they come
SAY = partial(print, flush=True)

KEY = "bench/write"


def time_calls(put: Callable[[bytes], object], count: int) -> tuple[float, float]:
    """(main-thread CPU us, wall us) per call."""
    payload = b"x" * 24
    wall0, cpu0 = time.perf_counter(), time.thread_time()
    for _ in range(count):
        put(payload)
    return (
        (time.thread_time() - cpu0) / count * 1e6,
        (time.perf_counter() - wall0) / count * 1e6,
    )


#: (label, subscriber's --transport, the Writer's QoS or None for a bare Zenoh publisher)
CASES: list[tuple[str, str, QosProfile | None]] = [
    ("plain Zenoh publisher put", "zenoh", None),
    ("arpz Writer KEEP_ALL", "arpz", QosProfile(history=HistoryPolicy.KEEP_ALL)),
    (
        "arpz Writer KEEP_ALL, unbatched",
        "arpz",
        QosProfile(history=HistoryPolicy.KEEP_ALL, batch_max_samples=1),
    ),
]


def measure(
    count: int,
    cases: list[tuple[str, str, QosProfile | None]] = CASES,
    log: Callable[[str], object] = SAY,
) -> list[tuple[str, float, float]]:
    """(label, main-thread CPU us, wall us) a call of each case, in turn."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    rows: list[tuple[str, float, float]] = []
    with perf_router(endpoint):
        transport = ZenohTransport.open(SessionSettings(mode="client", connect=[endpoint]))
        try:
            for label, kind, qos in cases:
                sub = _perf(
                    "sub", "--connect", endpoint, "--key", KEY, "--transport", kind,
                    "--count", str(count), "--history", "keep_all",
                )  # fmt: skip
                with child(sub, ready="ready"):
                    if qos is None:
                        publisher = transport.publisher(KEY)  # congestion control BLOCK
                        time.sleep(0.5)
                        cpu, wall = time_calls(publisher.put, count)
                        publisher.undeclare()
                    else:
                        with Writer(transport, KEY, qos) as writer:
                            while not writer.matched_count:
                                time.sleep(0.01)
                            writer.wait_for_acknowledgments(2.0)
                            cpu, wall = time_calls(writer.write, count)
                            writer.wait_for_acknowledgments(10.0)
                rows.append((label, cpu, wall))
                log(f"  {label:34s} {cpu:6.2f} us CPU  {wall:6.2f} us wall")
        finally:
            transport.close()
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--count", type=int, default=200_000)
    args = ap.parse_args()
    rows = measure(args.count)
    base = rows[0][1]
    print()
    print("| publish call (24 B) | main-thread CPU us | wall us | CPU / bare put |")
    print("|---|---|---|---|")
    for label, cpu, wall in rows:
        print(f"| {label} | {cpu:.2f} | {wall:.2f} | {cpu / base:.2f}x |")


if __name__ == "__main__":
    main()
