"""How long a sample lost right after a writer's quiet spell takes to arrive.

    python benchmarks/investigations/quiet_recovery.py [--base CHECKOUT] [--tries 5] [--idle-s 2]

A real ``Writer`` and ``Reader`` (RELIABLE, 0.1 s heartbeat) on the in-memory transport: after
``--idle-s`` seconds with nothing written (the writer goes quiet: docs/reliability.md, "Quiet
writers"), the next write's put is dropped, and the time until the reader gets that sample
(through the writer's heartbeat, the reader's NACK and the resend) is printed for each try. The
design's bound is ``QUIET_HEARTBEAT_S`` (1 s) instead of one heartbeat period; ``--base`` runs
the same in another checkout (a ``git worktree`` at the commit before a change) first.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parents[2]


def recovery_times(tries: int, idle_s: float) -> list[float]:
    """Seconds from the dropped write to its delivery, one a try (run inside a checkout)."""
    from arpz.channel.reader import Reader
    from arpz.channel.writer import Writer
    from arpz.core.protocol.qos import QosProfile
    from arpz.transport.memory import MemoryBus, MemoryTransport

    got: list[bytes] = []
    bus = MemoryBus()
    a, b = MemoryTransport(bus), MemoryTransport(bus)
    qos = QosProfile(heartbeat_period_s=0.1)
    reader = Reader(b, "t/quiet", qos, lambda payload, info: got.append(payload))
    writer = Writer(a, "t/quiet", qos)
    deadline = time.monotonic() + 5
    while writer.matched_count < 1 and time.monotonic() < deadline:
        time.sleep(0.01)
    writer.write(b"first")
    put = writer._put
    drop = [False]

    def dropping(payload: bytes, attachment: bytes | None = None) -> None:
        if drop[0]:
            drop[0] = False  # this one is lost on the "link"
            return
        put(payload, attachment=attachment)

    writer._put = dropping
    times = []
    try:
        for k in range(tries):
            time.sleep(idle_s)  # acknowledged, then nothing to say: quiet
            sample = b"lost-%d" % k
            drop[0] = True
            start = time.monotonic()
            writer.write(sample)
            while sample not in got:
                if time.monotonic() - start > 10:
                    raise SystemExit(f"{sample!r} never arrived")
                time.sleep(0.001)
            times.append(time.monotonic() - start)
    finally:
        writer.close()
        reader.close()
        a.close()
        b.close()
    return times


def run_in(checkout: Path, opts: argparse.Namespace) -> list[float]:
    env = {**os.environ, "PYTHONPATH": str(checkout)}
    command = [sys.executable, str(Path(__file__).resolve()), "--inner"]
    command += ["--tries", str(opts.tries), "--idle-s", str(opts.idle_s)]
    out = subprocess.run(command, cwd=checkout, env=env, capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"{checkout}: {out.stderr[-2000:]}")
    return [float(v) for v in out.stdout.split()]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--base", type=Path, help="another checkout, measured first")
    parser.add_argument("--tries", type=int, default=5)
    parser.add_argument("--idle-s", type=float, default=2.0, help="quiet spell before each try")
    parser.add_argument("--inner", action="store_true", help=argparse.SUPPRESS)
    opts = parser.parse_args()
    if opts.inner:
        print(" ".join(f"{t:.4f}" for t in recovery_times(opts.tries, opts.idle_s)))
        return
    sides = ([("base", opts.base.resolve())] if opts.base else []) + [("this", HERE)]
    for side, checkout in sides:
        times = run_in(checkout, opts)
        shown = ", ".join(f"{t * 1e3:.0f}" for t in times)
        print(
            f"{side}: lost sample after {opts.idle_s:g} s idle recovered in {shown} ms "
            f"(median {statistics.median(times) * 1e3:.0f}, max {max(times) * 1e3:.0f})",
            flush=True,
        )


if __name__ == "__main__":
    main()
