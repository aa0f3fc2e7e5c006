"""Thread wake-ups of a fleet worker and of its CEDDP at a low rate, per kind of thread.

    python benchmarks/investigations/idle_wakeups.py [--base CHECKOUT] [--robots 10] [--rate 1]
        [--window 10]

Runs ``python -m arpz.perf fleet --robots N --topics 8 --rate HZ --processes 1`` from this
checkout (and, with ``--base``, from another one, e.g. a ``git worktree`` at the commit before a
change: both in the same run, base first) and counts, from /proc/PID/task/*/status, the
voluntary context switches of every thread of the worker process and of the CEDDP over
``--window`` seconds of load; the worker's threads are grouped by their Python name (robot ids
and topic names folded). Each wake-up of a Python thread is a turn of its process's GIL: on a
robot (or the load generator's worker) they are CPU the robot's sensing loop does not get.
Prints wake-ups a second per kind and the totals, and the ratio this / base.

Linux only (reads /proc). Every Python thread is called "python" in /proc/PID/task/*/comm, so
the grouping by kind uses the Python names ``py-spy dump`` reports when py-spy is installed
(``pip install py-spy``); without it, only the totals are meaningful.
"""

from __future__ import annotations

import argparse
import collections
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import IO

HERE = Path(__file__).resolve().parents[2]


def switches(pid: int) -> dict[int, int]:
    """Voluntary context switches of every thread of ``pid``, by thread id."""
    out: dict[int, int] = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            status = Path(f"/proc/{pid}/task/{tid}/status").read_text()
        except OSError:
            continue
        match = re.search(r"^voluntary_ctxt_switches:\s+(\d+)", status, re.M)
        if match:
            out[int(tid)] = int(match.group(1))
    return out


def thread_names(pid: int) -> dict[int, str]:
    """Python thread names by thread id (``py-spy dump``), robot ids and topics folded."""
    if shutil.which("py-spy") is None:
        return {}
    dump = subprocess.run(
        ["py-spy", "dump", "--pid", str(pid)], capture_output=True, text=True, check=False
    ).stdout
    names = {}
    for tid, name in re.findall(r'^Thread (\d+) \([^)]*\): "(.*)"', dump, re.M):
        name = re.sub(r"c\d+-r\d+", "ROBOT", name)
        name = re.sub(r"/t\d\d\b", "/TOPIC", name)
        names[int(tid)] = re.sub(r"Thread-\d+ \(pyo3-closure\)", "zenoh callback", name)
    return names


def per_thread(before: dict[int, int], after: dict[int, int]) -> dict[int, int]:
    """Wake-ups of each thread between two ``switches`` readings (a thread born in between
    counts from zero; one that ended is left out)."""
    return {tid: count - before.get(tid, 0) for tid, count in after.items()}


def by_kind(counts: dict[int, int], names: dict[int, str]) -> dict[str, int]:
    kinds: collections.Counter[str] = collections.Counter()
    for tid, count in counts.items():
        kinds[names.get(tid, "(unnamed native thread)")] += count
    return dict(kinds)


def measure(checkout: Path, opts: argparse.Namespace) -> tuple[float, dict[str, float], float]:
    """(worker total, worker per kind, CEDDP total) for one run of ``perf fleet``."""
    env = {**os.environ, "PYTHONPATH": str(checkout)}
    command = [sys.executable, "-m", "arpz.perf", "fleet", "--robots", str(opts.robots)]
    command += ["--topics", "8", "--rate", str(opts.rate), "--processes", "1"]
    command += ["--duration", str(opts.window + 15)]
    with tempfile.TemporaryFile("w+") as log:
        proc = subprocess.Popen(command, cwd=checkout, env=env, stdout=log, stderr=log, text=True)
        try:
            deadline = time.monotonic() + 120
            while "running; logs in" not in _read(log):
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise SystemExit(f"perf fleet did not start:\n{_read(log)[-2000:]}")
                time.sleep(0.5)
            time.sleep(3)  # the first reports and matches settle
            worker = _child(proc.pid, "fleet-worker")
            ceddp = _child(proc.pid, "arpz.ceddp")
            # both processes over the same window; the names are read after it (py-spy stops
            # the worker for a moment)
            worker_before, ceddp_before = switches(worker), switches(ceddp)
            time.sleep(opts.window)
            worker_after, ceddp_after = switches(worker), switches(ceddp)
            kinds = by_kind(per_thread(worker_before, worker_after), thread_names(worker))
            ceddp_total = sum(per_thread(ceddp_before, ceddp_after).values())
            proc.wait(timeout=opts.window + 120)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    rates = {kind: count / opts.window for kind, count in kinds.items()}
    return sum(rates.values()), rates, ceddp_total / opts.window


def _read(log: IO[str]) -> str:
    log.seek(0)
    return log.read()


def _child(parent: int, marker: str) -> int:
    """The pid of ``parent``'s child whose command line contains ``marker``."""
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
            cmdline = Path(f"/proc/{entry}/cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue
        if int(stat.rpartition(")")[2].split()[1]) == parent and marker in cmdline:
            return int(entry)
    raise SystemExit(f"no child process of {parent} runs {marker}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--base", type=Path, help="another checkout, measured first")
    parser.add_argument("--robots", type=int, default=10)
    parser.add_argument("--rate", type=float, default=1.0, help="Hz per topic (1)")
    parser.add_argument("--window", type=float, default=10.0, help="seconds counted (10)")
    opts = parser.parse_args()
    sides = ([("base", opts.base.resolve())] if opts.base else []) + [("this", HERE)]
    totals = {}
    for side, checkout in sides:
        print(f"{side}: {checkout}, {opts.robots} robots x 8 topics x {opts.rate:g} Hz", flush=True)
        total, kinds, ceddp = measure(checkout, opts)
        totals[side] = (total, ceddp)
        for kind, rate in sorted(kinds.items(), key=lambda kv: -kv[1])[:12]:
            print(f"  {rate:8.0f}/s  {kind}")
        print(
            f"  worker {total:,.0f} wake-ups/s ({total / opts.robots:,.0f} a robot), CEDDP "
            f"{ceddp:,.0f}/s",
            flush=True,
        )
    if len(totals) == 2:
        (bw, bc), (tw, tc) = totals["base"], totals["this"]
        print(f"this / base: worker {tw / bw:.2f}x, CEDDP {tc / bc:.2f}x")


if __name__ == "__main__":
    main()
