"""A/B of the fleet load test: another checkout against this one, runs alternating.

    python benchmarks/fleet_ab.py BASE [--this CHECKOUT] [--rounds 3] [-- perf fleet arguments]
    python benchmarks/fleet_ab.py . --base-extra="--robot-phases aligned"   # an option's A/B

Runs ``python -m arpz.perf fleet`` (default ``--robots 50 --topics 8 --rate 100 --processes 4
--duration 20``) from BASE (a ``git worktree`` at the commit before a change) and from this
checkout (or ``--this``) in turn, ``--rounds`` times each, so that both sides see the same slow
and fast windows of a shared host (``--base-extra`` / ``--this-extra``: arguments added to
one side only, for the A/B of an option in one checkout); prints each run's figures and the
medians of each side with their ratio (this / base). The CEDDP's time per sample ("time in the
CEDDP", summary.json ``ingest.sojourn_ms_*``) is printed where the checkout measures it (n/a
before stop 36).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent.parent
DEFAULT = ["--robots", "50", "--topics", "8", "--rate", "100", "--processes", "4"]
DEFAULT += ["--duration", "20"]
#: (label, where in the JSON, format)
FIGURES = [
    ("delivered/s", ("fleet", "delivered_per_s"), "{:,.0f}"),
    ("of offered", ("fleet", "delivered_ratio"), "{:.3f}"),
    ("p99 ms", ("fleet", "latency_ms_p99"), "{:.1f}"),
    # the worst robot's p99 is often one robot's outlier (RESULTS.md, stop 36): the median
    # robot's tells a change from noise sooner
    ("median robot p99 ms", ("fleet", "latency_ms_p99_median_robot"), "{:.1f}"),
    ("max ms", ("fleet", "latency_ms_max"), "{:.0f}"),
    ("in CEDDP p99 ms", ("ceddp", "sojourn_ms_p99"), "{:.1f}"),
    ("queue p99 ms", ("ceddp", "ingest_backlog_ms_p99"), "{:.1f}"),
    ("CEDDP cores", ("fleet", "ceddp_cpu_cores"), "{:.2f}"),
    ("lost", ("fleet", "lost"), "{:.0f}"),
    # 0.015 cores or more went with a worst-robot p99 of 13-82 ms at 50 robots (stop 42): a
    # round whose two sides differ in it compares the hypervisor, not the change
    ("host stolen cores", ("fleet", "host_steal_cores"), "{:.3f}"),
]


def figure(doc: dict[str, Any], where: tuple[str, str]) -> Any:
    part, key = where
    row = doc["fleet"] if part == "fleet" else (doc.get("ceddps") or [{}])[0]
    return row.get(key)


def run(checkout: Path, args: list[str], out: Path) -> dict[str, Any]:
    env = {**os.environ, "PYTHONPATH": str(checkout)}
    cmd = [sys.executable, "-m", "arpz.perf", "fleet", *args, "--json", str(out)]
    proc = subprocess.run(cmd, cwd=checkout, env=env, capture_output=True, text=True)
    if proc.returncode not in (0, 1) or not out.exists():
        raise SystemExit(f"fleet_ab: {checkout} failed ({proc.returncode}): {proc.stderr[-2000:]}")
    doc: dict[str, Any] = json.loads(out.read_text())
    return doc


def show(label: str, doc: dict[str, Any]) -> str:
    cells = []
    for name, where, fmt in FIGURES:
        value = figure(doc, where)
        cells.append(f"{name} {'n/a' if value is None else fmt.format(value)}")
    failed = "" if doc["fleet"].get("reconciled") else "  NOT RECONCILED"
    stolen = "  STOLEN" if doc["fleet"].get("steal_flagged") else ""
    return f"{label:>5}: " + ", ".join(cells) + failed + stolen


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("base", type=Path, help="the other checkout (a git worktree)")
    ap.add_argument("--this", type=Path, default=HERE, help="the checkout under test (this one)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--base-extra", default="", help="perf fleet arguments of the base only")
    ap.add_argument("--this-extra", default="", help="perf fleet arguments of this side only")
    # split at "--" by hand: argparse gives a trailing ``nargs="*"`` positional nothing once
    # ``base`` and an option came before it ("unrecognized arguments")
    argv = sys.argv[1:]
    cut = argv.index("--") if "--" in argv else len(argv)
    opts = ap.parse_args(argv[:cut])
    args = argv[cut + 1 :] or DEFAULT
    sides = {"base": opts.base.resolve(), "this": opts.this.resolve()}
    docs: dict[str, list[dict[str, Any]]] = {"base": [], "this": []}
    out = Path(tempfile.mkdtemp(prefix="fleet-ab-"))
    print(
        f"fleet_ab: perf fleet {' '.join(args)}; base {sides['base']} {opts.base_extra}, "
        f"this {sides['this']} {opts.this_extra}"
    )
    for round_ in range(1, opts.rounds + 1):
        for side, checkout in sides.items():
            started = time.monotonic()
            extra = (opts.base_extra if side == "base" else opts.this_extra).split()
            doc = run(checkout, args + extra, out / f"{side}{round_}.json")
            docs[side].append(doc)
            took = time.monotonic() - started
            print(f"round {round_}/{opts.rounds} ({took:.0f} s) " + show(side, doc), flush=True)
    print("medians:")
    for name, where, fmt in FIGURES:
        meds = {}
        for side in sides:
            values = [v for v in (figure(d, where) for d in docs[side]) if v is not None]
            meds[side] = statistics.median(values) if values else None
        base, this = meds["base"], meds["this"]
        ratio = f"{this / base:.2f}x" if base and this is not None else "n/a"
        cells = ["n/a" if v is None else fmt.format(v) for v in (base, this)]
        print(f"  {name:>19}: base {cells[0]}, this {cells[1]} ({ratio})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
