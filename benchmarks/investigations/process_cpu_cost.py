"""What reading the process's CPU time costs a robot, by the number of threads in its process.

A robot reports its process's CPU share twice a second. ``time.process_time()`` asks Linux for
the CPU time of the whole process, which it sums over every thread (with the GIL held, in
Python); a robot process has about 60 threads, a ``python -m arpz.perf fleet`` worker of a dozen
robots about 750 (issue 17). Measured here with 1, 60 and 750 threads that wake every 10 ms (as
the channels' workers and zenoh-python's callback threads do), against ``PROCESS_CPU.read()``
(arpz.robot.process_cpu), which reads at most once every 0.2 s for all the robots of a
process: the time a second a worker's dozen robots spend reading, either way.

    python benchmarks/investigations/process_cpu_cost.py [--calls 300]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from arpz.robot.process_cpu import MIN_INTERVAL_S

#: a fleet worker's robots (50 in 4 processes) and each one's reports a second
ROBOTS, REPORTS_HZ = 12, 2.0


def call_costs_us(calls: int) -> list[float]:
    """Wall time of each ``time.process_time()`` call, one every 2 ms."""
    costs = []
    for _ in range(calls):
        start = time.perf_counter()
        time.process_time()
        costs.append((time.perf_counter() - start) * 1e6)
        time.sleep(0.002)
    return costs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=300)
    args = parser.parse_args()
    stop = threading.Event()

    def waking() -> None:
        while not stop.is_set():
            stop.wait(0.01)

    threads: list[threading.Thread] = []
    try:
        for count in (1, 60, 750):
            while threading.active_count() < count:
                thread = threading.Thread(target=waking, daemon=True)
                thread.start()
                threads.append(thread)
            time.sleep(0.5)
            costs = call_costs_us(args.calls)
            median = statistics.median(costs)
            direct = ROBOTS * REPORTS_HZ * median  # us of GIL-held time a second
            shared = min(ROBOTS * REPORTS_HZ, 1 / MIN_INTERVAL_S) * median
            print(
                f"{threading.active_count():4d} threads: time.process_time() median {median:6.1f}"
                f" us (p90 {statistics.quantiles(costs, n=10)[-1]:6.1f}); {ROBOTS} robots "
                f"reporting: read at each report {direct / 1000:5.2f} ms/s, through "
                f"PROCESS_CPU {shared / 1000:5.2f} ms/s ({shared / direct:.2f}x)",
                flush=True,
            )
    finally:
        stop.set()
        for thread in threads:
            thread.join()


if __name__ == "__main__":
    main()
