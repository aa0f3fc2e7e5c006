"""CPU by thread of a running process over an interval: what each of a CEDDP's threads costs,
Zenoh's native ones (``rx-N``, ``tx-N``) included, which a Python profiler does not see.

CPU comes from /proc/PID/task/*/stat (utime + stime), wake-ups from the voluntary context
switches in /proc/PID/task/*/status; Python thread names from ``py-spy dump``
(py-spy's thread ids are the native ones), other threads keep their kernel name. Names are folded
as ``profile_shares.py`` folds them, so 25 robots' Hello writers show as one row with a count.
How stop 28 of issue 17 read an idle fleet's CEDDP (README.md here):

    python -m arpz.perf fleet --robots 25 --topics 8 --rate 1 --processes 2 --duration 40 \\
        --workdir /tmp/f &
    sleep 20;
    python benchmarks/investigations/thread_cpu.py "$(pgrep -f 'arpz.ceddp --config /tmp/f')" 10
"""

from __future__ import annotations

import argparse
import collections
import os
import re
import shutil
import subprocess
import time
from pathlib import Path

from profile_shares import thread_row  # benchmarks/: one folding of thread names

_TICK_S = 1 / os.sysconf("SC_CLK_TCK")
_THREAD = re.compile(r'Thread (\d+) \([^)]*\): "([^"]*)"')
_SWITCHES = re.compile(r"^voluntary_ctxt_switches:\s+(\d+)", re.MULTILINE)


def cpu_by_thread(pid: int) -> dict[int, tuple[str, float, int]]:
    """tid -> (kernel name, CPU seconds so far, wake-ups so far: voluntary context switches,
    each a sleep the thread woke from)."""
    out: dict[int, tuple[str, float, int]] = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            stat = (task / "stat").read_text()
            comm = (task / "comm").read_text().strip()
            status = (task / "status").read_text()
        except OSError:  # the thread ended meanwhile
            continue
        fields = stat[stat.rfind(")") + 2 :].split()
        switches = _SWITCHES.search(status)
        out[int(task.name)] = (
            comm,
            (int(fields[11]) + int(fields[12])) * _TICK_S,
            int(switches.group(1)) if switches else 0,
        )
    return out


def python_names(pid: int) -> dict[int, str]:
    """tid -> Python thread name, from ``py-spy dump`` (empty without py-spy)."""
    if shutil.which("py-spy") is None:
        return {}
    dump = subprocess.run(["py-spy", "dump", "--pid", str(pid)], capture_output=True, text=True)
    return {int(m.group(1)): m.group(2) for m in _THREAD.finditer(dump.stdout)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("pid", type=int)
    ap.add_argument("seconds", type=float, nargs="?", default=10.0)
    ap.add_argument("--top", type=int, default=20)
    args = ap.parse_args()
    names = python_names(args.pid)
    before, t0 = cpu_by_thread(args.pid), time.monotonic()
    time.sleep(args.seconds)
    after, elapsed = cpu_by_thread(args.pid), time.monotonic() - t0
    cpu: collections.Counter[str] = collections.Counter()
    wakes: collections.Counter[str] = collections.Counter()
    count: collections.Counter[str] = collections.Counter()
    for tid, (comm, seconds, switches) in after.items():
        row = thread_row(names.get(tid, comm))
        _, seconds_before, switches_before = before.get(tid, (comm, 0.0, 0))
        cpu[row] += seconds - seconds_before
        wakes[row] += switches - switches_before
        count[row] += 1
    total = sum(cpu.values())
    print(
        f"pid {args.pid}: {total / elapsed:.3f} cores over {elapsed:.1f} s, {len(after)} threads, "
        f"{sum(wakes.values()) / elapsed:,.0f} wake-ups/s"
    )
    for row, seconds in cpu.most_common(args.top):
        print(
            f"  {seconds / elapsed * 1e3:8.1f} ms/s {wakes[row] / elapsed:9,.0f} wake-ups/s"
            f"  x{count[row]:<4} {row}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
