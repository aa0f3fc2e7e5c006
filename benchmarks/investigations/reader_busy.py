"""What a reader's ``busy`` and ``tick`` cost with a fleet's writers behind one wildcard
subscription.

The channel asks its reader machine ``busy()`` after every pass of its delivery thread (does a
gap now need the fine timer?). By its definition it looks at every matched writer; the machine
keeps the writers that may be busy (its suspects) and looks at those only. A CEDDP's sensor
reader has robots x topics writers (400 for the issue-17 target), all in order most of the time.
This matches that many writers to one reader, brings each in sync with one sample, and times
``busy()`` against ``busy_scan()`` (the definition) in the same run. It also times ``tick()``:
a full one polls every writer's deadline and lease (once a ``_full_period_s``, and what every
tick did before), a fine one (every few ms while the reader is busy) looks at the suspects only.

    python benchmarks/investigations/reader_busy.py [--robots 10,50,100] [--topics 8]
        [--calls 20000]
"""

from __future__ import annotations

import argparse
import math
import random
import sys
import time
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from arpz.core.protocol._common import new_guid
from arpz.core.protocol.qos import HistoryPolicy, QosProfile
from arpz.core.protocol.reader_machine import ReaderMachine
from arpz.core.protocol.timers import FakeClock
from arpz.core.protocol.writer_machine import WriterMachine
from tests.unit.reliability.lossy_bus import Link, LossyBus


def synced_reader(robots: int, topics: int) -> ReaderMachine:
    """One reader of ``f/robot/*/sensor/*`` matched to robots x topics writers over the tests'
    in-memory bus (no loss), each writer in sync and one sample delivered."""
    bus = LossyBus(random.Random(1), Link(), FakeClock())
    qos = QosProfile(history=HistoryPolicy.KEEP_ALL, max_samples=30)
    writers = [
        bus.add(WriterMachine(f"f/robot/r{r}/sensor/s{t}", qos, new_guid(), bus.clock))
        for r in range(robots)
        for t in range(topics)
    ]
    reader = bus.add(ReaderMachine("f/robot/*/sensor/*", qos, new_guid(), bus.clock))
    bus.run_for(0.3)
    for writer in writers:
        bus.write(writer, b"x")
    bus.run_for(1.0)
    assert isinstance(reader.machine, ReaderMachine)
    return reader.machine


def full_tick(reader: ReaderMachine) -> None:
    """A tick that polls every writer (as every tick did before)."""
    reader._next_full_s = -math.inf
    reader.tick()


def per_call_us(fn: Callable[[], object], calls: int) -> float:
    start = time.perf_counter()
    for _ in range(calls):
        fn()
    return (time.perf_counter() - start) / calls * 1e6


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robots", default="10,50,100")
    ap.add_argument("--topics", type=int, default=8)
    ap.add_argument("--calls", type=int, default=20_000)
    args = ap.parse_args()
    print(
        f"{'writers':>8} {'synced':>7} {'busy() us':>10} {'scan us':>9} {'ratio':>7} "
        f"{'fine tick us':>13} {'full tick us':>13} {'ratio':>7}"
    )
    for robots in (int(n) for n in args.robots.split(",")):
        reader = synced_reader(robots, args.topics)
        synced = sum(p.synced for p in reader.writers.values())
        assert reader.busy() == reader.busy_scan()
        fast = per_call_us(reader.busy, args.calls)
        scan = per_call_us(reader.busy_scan, max(args.calls // 20, 100))
        fine = per_call_us(reader.tick, args.calls)  # the clock stands still: no full tick due

        full = per_call_us(lambda r=reader: full_tick(r), max(args.calls // 20, 100))
        print(
            f"{len(reader.writers):>8} {synced:>7} {fast:>10.2f} {scan:>9.2f} {fast / scan:>6.3f}x "
            f"{fine:>13.2f} {full:>13.2f} {fine / full:>6.3f}x"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
