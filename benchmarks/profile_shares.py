"""Where a process spends its Python time, from a py-spy profile: the share of samples by
thread and by function (inclusive and self).

How stop 27 of issue 17 found the CEDDP's cost a robot (benchmarks/RESULTS.md): run a fleet,
sample its CEDDP with py-spy (``pip install py-spy``; root, or ptrace allowed) holding the GIL
only, so that the shares are of Python time, not of threads waiting:

    python -m arpz.perf fleet --robots 25 --topics 8 --rate 1 --duration 45 --workdir /tmp/f &
    py-spy record --pid "$(pgrep -f 'arpz.ceddp --config /tmp/f')" --duration 20 --rate 200 \\
        --gil --threads --format raw -o /tmp/f/raw.txt
    python benchmarks/profile_shares.py /tmp/f/raw.txt [--top 40]

Thread names are folded (a robot's name, a thread number and a pid become one row), so the 25
Hello writers of 25 robots show as one.
"""

from __future__ import annotations

import argparse
import collections
import re
from pathlib import Path

_LINE = re.compile(r":\d+\)")


def thread_row(frame: str) -> str:
    """``thread (1234): arpz-writer-.../robot/c0-r007/cmd/hello`` as one row for every robot."""
    name = re.sub(r"\(\d+\)", "", frame)
    name = re.sub(r"Thread-\d+", "Thread-N", name)
    return re.sub(r"c\d+-r\d+", "ROBOT", name)


def shares(raw: str) -> tuple[int, dict[str, collections.Counter[str]]]:
    """(samples, {"thread": ..., "inclusive": ..., "self": ...}) of py-spy's raw output: one
    line a stack, ``thread;frame;...;frame count``."""
    counters = {k: collections.Counter[str]() for k in ("thread", "inclusive", "self")}
    total = 0
    for line in raw.splitlines():
        stack, _, count = line.rpartition(" ")
        if not stack:
            continue
        n = int(count)
        frames = [_LINE.sub(")", f) for f in stack.split(";")]
        total += n
        counters["thread"][thread_row(frames[0])] += n
        for function in set(frames[1:]):
            counters["inclusive"][function] += n
        counters["self"][frames[-1]] += n
    return total, counters


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("raw", type=Path, help="py-spy record --format raw output")
    ap.add_argument("--top", type=int, default=30)
    args = ap.parse_args()
    total, counters = shares(args.raw.read_text())
    print(f"{total} samples")
    for kind, counter in counters.items():
        print(f"--- by {kind}")
        for name, n in counter.most_common(args.top):
            print(f"{100 * n / total:5.1f} %  {name[:150]}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
