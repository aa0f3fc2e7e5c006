"""What the same work costs when it comes back to back and when it comes after a pause: a fixed
piece of pure Python, and a Zenoh put of 600 B (a robot's bundle) to a router in another process
with a subscriber, on the CPU of the calling thread, of this process and of the router's.

A fleet at 100 Hz a topic hands every process a message every few milliseconds with pauses in
between; ``benchmarks/ceddp_ingest.py`` streams. On this shared VM the pause alone makes the same
work cost several times more (caches and the scheduler's state gone cold: a busy neighbour
process does not help), which is why the CEDDP's and the robots' CPU a sample in
``python -m arpz.perf fleet`` is far above the streaming figures (benchmarks/RESULTS.md, issue 17).

    python benchmarks/investigations/intermittent_cost.py [--gaps-ms 0,1,10]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from arpz.core.transport import SessionSettings  # noqa: E402
from arpz.perf.zenoh_baselines import open_session  # noqa: E402
from arpz.tools.launch import free_port  # noqa: E402

ROUTER = r"""
import os, sys, time
from arpz.perf.zenoh_baselines import open_session
from arpz.core.transport import SessionSettings
session = open_session(SessionSettings(mode="router", listen=[sys.argv[1]]))
count = [0]
sub = session.declare_subscriber("bench/**", lambda _s: count.__setitem__(0, count[0] + 1))
print("up", flush=True)
for _line in sys.stdin:
    print(count[0], time.process_time(), flush=True)
os._exit(0)
"""


def python_work() -> int:
    total = 0
    for i in range(300):
        total += i * i
    return total


def cpu_us(call: Callable[[], object], gap_s: float, count: int) -> tuple[float, float]:
    """(calling thread, whole process) CPU microseconds a call, pauses included."""
    thread0, process0 = time.thread_time(), time.process_time()
    for _ in range(count):
        call()
        if gap_s:
            time.sleep(gap_s)
    return (
        (time.thread_time() - thread0) / count * 1e6,
        (time.process_time() - process0) / count * 1e6,
    )


def _gaps_ms(text: str) -> list[float]:
    try:
        gaps = [float(g) for g in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a list of milliseconds: {text!r}") from None
    if not gaps or any(g < 0 or g > 1000 for g in gaps):
        raise argparse.ArgumentTypeError(f"each pause must be 0 to 1000 ms: {text!r}")
    return gaps


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument(
        "--gaps-ms", type=_gaps_ms, default=[0.0, 1.0, 10.0], help="pauses between calls, ms"
    )
    args = parser.parse_args()
    gaps = [g / 1000 for g in args.gaps_ms]
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = subprocess.Popen(
        [sys.executable, "-c", ROUTER, endpoint],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    assert router.stdin is not None and router.stdout is not None
    try:
        if router.stdout.readline().strip() != "up":
            raise RuntimeError("the router process did not start")

        def router_state() -> tuple[int, float]:
            assert router.stdin is not None and router.stdout is not None
            router.stdin.write("\n")
            router.stdin.flush()
            received, cpu = router.stdout.readline().split()
            return int(received), float(cpu)

        session = open_session(SessionSettings(mode="client", connect=[endpoint]))
        publisher = session.declare_publisher("bench/put")
        time.sleep(1.0)
        payload = bytes(600)
        print("CPU a call, us: python work (calling thread) | zenoh put (calling thread / this")
        print("process / the router process), the pause's own cost taken out; ratios to the")
        print("first pause's figure")
        first: tuple[float, float] | None = None
        for gap in gaps:
            count = 3000 if gap < 0.005 else 300
            # the pauses alone, in both processes: taken out of the figures below
            _, router0 = router_state()
            idle_thread, idle_process = cpu_us(lambda: None, gap, count)
            _, router1 = router_state()
            work_us = cpu_us(python_work, gap, count)[0] - idle_thread
            received0, router2 = router_state()
            thread_us, process_us = cpu_us(lambda: publisher.put(payload), gap, count)
            time.sleep(0.1)  # the last puts reach the router
            received1, router3 = router_state()
            thread_us, process_us = thread_us - idle_thread, process_us - idle_process
            router_us = ((router3 - router2) - (router1 - router0)) / count * 1e6
            first = first or (work_us, process_us)
            print(
                f"  gap {gap * 1e3:4g} ms: python work {work_us:6.1f} ({work_us / first[0]:.1f}x)"
                f" | zenoh put {thread_us:6.1f} / {process_us:6.1f} / {router_us:6.1f}"
                f" ({process_us / first[1]:.0f}x); {received1 - received0} of {count} arrived",
                flush=True,
            )
    finally:
        router.kill()
        router.wait()
    os._exit(0)  # a Zenoh session's close can hang at exit with the router gone


if __name__ == "__main__":
    raise SystemExit(main())
