"""How the writer's heartbeat period sets the tail of recovery on a lossy link (issue 20).

The pure channel machines (a WriterMachine and a ReaderMachine on the in-memory lossy bus of
tests/unit/reliability/lossy_bus.py, simulated time, no Python or Zenoh scheduling noise): one
writer at each rate, i.i.d. loss each way, a fixed one-way delay. Prints the delivery latency
(write to in-order delivery) p50/p90/p99/max, the resends and the heartbeats per second for each
heartbeat period, so the closed QoS loop's ``heartbeat_rtts`` rule can be judged against the
profile's 0.1 s without the tens of milliseconds of run-to-run noise a real fleet run has.

    python benchmarks/investigations/recovery_heartbeat.py [--loss 9] [--delay-ms 5]
        [--seconds 60] [--seeds 3]
"""

from __future__ import annotations

import argparse
import os
import random
import struct
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from arpz.core.protocol.qos import QosProfile  # noqa: E402
from arpz.core.protocol.reader_machine import ReaderMachine  # noqa: E402
from arpz.core.protocol.timers import FakeClock  # noqa: E402
from arpz.core.protocol.writer_machine import WriterMachine  # noqa: E402
from tests.unit.reliability.lossy_bus import Link, LossyBus  # noqa: E402

STEP_S = 0.001


def run(
    rate_hz: float, heartbeat_s: float, *, loss: float, delay_s: float, seconds: float, seed: int
) -> tuple[list[float], int, int]:
    """(latencies in s, resends, heartbeats) of one writer -> reader run."""
    clock = FakeClock()
    bus = LossyBus(random.Random(seed), Link(loss=loss, delay_s=delay_s), clock)
    writer = bus.add(
        WriterMachine(
            "t/a", QosProfile(depth=1000, heartbeat_period_s=heartbeat_s), os.urandom(8), clock
        )
    )
    reader = bus.add(ReaderMachine("t/a", QosProfile(depth=1000), os.urandom(8), clock))
    bus.run_for(0.5)  # match first
    latencies: list[float] = []
    next_write, end = clock.now_s, clock.now_s + seconds
    while clock.now_s < end:
        if clock.now_s >= next_write:
            bus.write(writer, struct.pack("d", clock.now_s))
            next_write += 1.0 / rate_hz
        bus.step(STEP_S)
        while len(reader.delivered) > len(latencies):
            payload, _ = reader.delivered[len(latencies)]
            latencies.append(clock.now_s - struct.unpack("d", payload)[0])
    machine = writer.machine
    assert isinstance(machine, WriterMachine)
    return latencies, machine.retransmitted, machine.heartbeats


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--loss", type=float, default=9.0, help="loss each way, %% (default 9)")
    parser.add_argument("--delay-ms", type=float, default=5.0, help="one-way delay, ms")
    parser.add_argument("--seconds", type=float, default=60.0, help="simulated seconds per run")
    parser.add_argument("--seeds", type=int, default=3, help="runs per cell")
    parser.add_argument("--rates", default="13.3,24", help="writer rates, Hz")
    parser.add_argument("--heartbeats", default="0.1,0.035,0.024,0.02", help="periods, s")
    args = parser.parse_args()
    started = time.monotonic()
    print(
        f"{args.loss:g} % loss each way, {args.delay_ms:g} ms one way, "
        f"{args.seeds} x {args.seconds:g} s simulated per cell"
    )
    print(
        f"{'rate Hz':>7} {'heartbeat s':>11} {'delivered':>9} {'p50 ms':>6} {'p90 ms':>6} "
        f"{'p99 ms':>6} {'max ms':>6} {'resent':>6} {'HB/s':>5}"
    )
    for rate in (float(r) for r in args.rates.split(",")):
        baseline = None
        for heartbeat in (float(h) for h in args.heartbeats.split(",")):
            lat: list[float] = []
            resent = beats = 0
            for seed in range(args.seeds):
                one, r, b = run(
                    rate,
                    heartbeat,
                    loss=args.loss / 100,
                    delay_s=args.delay_ms / 1000,
                    seconds=args.seconds,
                    seed=seed,
                )
                lat += one
                resent += r
                beats += b
            lat.sort()

            def q(p: float, lat: list[float] = lat) -> float:
                return lat[int(p * (len(lat) - 1))] * 1000

            p99 = q(0.99)
            baseline = baseline or p99
            print(
                f"{rate:>7g} {heartbeat:>11g} {len(lat):>9} {q(0.5):>6.1f} {q(0.9):>6.1f} "
                f"{p99:>6.1f} {lat[-1] * 1000:>6.1f} {resent:>6} "
                f"{beats / (args.seeds * args.seconds):>5.1f}   p99 {p99 / baseline:.2f}x "
                f"of the first period's"
            )
    print(f"({time.monotonic() - started:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
