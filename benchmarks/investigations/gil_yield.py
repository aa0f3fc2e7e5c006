"""How long a thread that gave up the GIL waits to get it back while a pure-Python loop runs,
with the CEDDP's ``Pacer`` in the loop and without (issue 17, stop 36).

    python benchmarks/investigations/gil_yield.py [--seconds 1] [--rounds 3]

The waiting thread stands for the sensor path's delivery thread, which gives the GIL up each
time it blocks for data; the loop for the metrics tick, the summary or the dashboard's flush.
Unpaced, the waiter gets the GIL back only when CPython's switch interval (5 ms by default)
forces the loop out; paced, at the loop's next yield. Prints the median and the 99th
percentile of the waits of each side (the best of ``--rounds``) and the ratio.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from arpz.ceddp.pacing import Pacer
from tests.support import gil_waits_ms


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seconds", type=float, default=1.0)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    print(f"switch interval {sys.getswitchinterval() * 1e3:.1f} ms")
    medians = {}
    for label, make in (("unpaced", lambda: None), ("paced", Pacer)):
        best: list[float] | None = None
        for _ in range(args.rounds):
            w = sorted(gil_waits_ms(make(), args.seconds))
            if best is None or statistics.median(w) < statistics.median(best):
                best = w
        assert best
        medians[label] = statistics.median(best)
        p99 = best[min(len(best) - 1, int(0.99 * len(best)))]
        print(
            f"{label:>8}: median wait {medians[label]:.2f} ms, p99 {p99:.2f} ms ({len(best)} waits)"
        )
    print(f"paced / unpaced (median): {medians['paced'] / medians['unpaced']:.2f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
