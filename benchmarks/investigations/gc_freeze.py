"""What a full garbage collection costs the CEDDP with and without its start-up frozen.

    python benchmarks/investigations/gc_freeze.py [--objects 30000] [--rounds 5]

Each side runs in a fresh process that imports what a CEDDP imports at start-up (arpz.ceddp's
server and dashboard: numpy, cvxpy, rerun, pyarrow, zenoh), freezes it or not
(``arpz.ceddp.__main__.freeze_start_up``), then allocates ``--objects`` containers standing in
for what a running CEDDP holds (at 50 robots 22 000-30 000 tracked objects besides start-up's,
counted in stop 36), and times ``gc.collect()``: the pause a full pass puts on every thread,
the sensor path's included, since it holds the GIL throughout. Prints the objects each pass
walks and the median pass of each side, and their ratio. The run-time objects are a stand-in
(a real CEDDP's passes under load took 10-12 ms of CPU frozen, measured with gc callbacks in
stop 36: its heap churns more than this one); the start-up is the CEDDP's own.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parents[2]

CHILD = """
import gc, json, sys, time
import arpz.ceddp.server, arpz.ceddp.dashboard, arpz.transport.zenoh  # the CEDDP's start-up
import cvxpy  # imported by the QoS optimiser when it solves
freeze, objects, rounds = sys.argv[1] == "1", int(sys.argv[2]), int(sys.argv[3])
if freeze:
    from arpz.ceddp.__main__ import freeze_start_up
    freeze_start_up()
held = [{"robot": i, "topics": [i, i + 1]} for i in range(objects // 2)]
walked = len(gc.get_objects())
passes = []
for _ in range(rounds):
    t0 = time.perf_counter()
    gc.collect()
    passes.append((time.perf_counter() - t0) * 1e3)
print(json.dumps({"walked": walked, "frozen": gc.get_freeze_count(), "passes_ms": passes}))
"""


def side(freeze: bool, objects: int, rounds: int) -> dict[str, object]:
    out = subprocess.run(
        [sys.executable, "-c", CHILD, "1" if freeze else "0", str(objects), str(rounds)],
        cwd=HERE,
        capture_output=True,
        text=True,
        check=True,
    )
    result: dict[str, object] = json.loads(out.stdout.strip().splitlines()[-1])
    return result


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--objects", type=int, default=30_000)
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    medians = {}
    for freeze in (False, True):
        started = time.monotonic()
        r = side(freeze, args.objects, args.rounds)
        passes = [float(p) for p in r["passes_ms"]]  # type: ignore[attr-defined]
        medians[freeze] = statistics.median(passes)
        label = "frozen start-up" if freeze else "as before"
        print(
            f"{label:>15}: a full pass walks {r['walked']:,} objects ({r['frozen']:,} frozen), "
            f"median {medians[freeze]:.1f} ms of {len(passes)} "
            f"({', '.join(f'{p:.1f}' for p in passes)}); {time.monotonic() - started:.0f} s",
            flush=True,
        )
    print(f"frozen / as before: {medians[True] / medians[False]:.2f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
