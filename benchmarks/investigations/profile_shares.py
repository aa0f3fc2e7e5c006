"""Where a process spends its Python time, from a py-spy profile: the share of samples by
thread and by function (inclusive and self).

How stop 27 of issue 17 found the CEDDP's cost a robot (README.md here): run a fleet,
sample its CEDDP with py-spy (``pip install py-spy``; root, or ptrace allowed) holding the GIL
only, so that the shares are of Python time, not of threads waiting:

    python -m arpz.perf fleet --robots 25 --topics 8 --rate 1 --duration 45 --workdir /tmp/f &
    py-spy record --pid "$(pgrep -f 'arpz.ceddp --config /tmp/f')" --duration 20 --rate 200 \\
        --gil --threads --format raw -o /tmp/f/raw.txt
    python benchmarks/investigations/profile_shares.py /tmp/f/raw.txt [--top 40]

``--within sense --lines``: the lines inside one function's calls (how stop 40 found what a
robot's ``sense`` spends, in a profile of ``benchmarks/investigations/robot_tick_cost.py --hot``).

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


_PROCESS = re.compile(r'process (\d+):"')
_THREAD_FRAME = "thread ("


def stacks(raw: str, *, lines: bool = False) -> list[tuple[str, list[str], int]]:
    """(thread, function frames, samples) of each stack of py-spy's raw output, a stack a line:
    ``[process...;]thread (tid): name;frame;...;frame count``. With ``--subprocesses`` a process
    frame carries the command line, which may hold newlines, quotes and semicolons (``python -c``
    scripts): a stack ends at the first line ending in a count, and the thread frame (``--threads``
    is needed) marks where the functions begin; the thread is named with the last process's pid."""
    out: list[tuple[str, list[str], int]] = []
    pending: list[str] = []
    for line in raw.splitlines():
        pending.append(line)
        stack, _, count = line.rpartition(" ")
        if not (stack and count.isdigit()):
            continue
        text = "\n".join(pending).rpartition(" ")[0]
        at = 0 if text.startswith(_THREAD_FRAME) else text.find(";" + _THREAD_FRAME) + 1
        if at == 0 and not text.startswith(_THREAD_FRAME):
            continue  # a line of a command line that happens to end in a number
        pending = []
        frames = text[at:].split(";")
        if not lines:  # a function's lines as one row
            frames = [_LINE.sub(")", f) for f in frames]
        pids = _PROCESS.findall(text[:at])
        thread = (f"process {pids[-1]}: " if pids else "") + thread_row(frames[0])
        out.append((thread, frames[1:], int(count)))
    if any(p.strip() for p in pending):
        raise ValueError(
            f"py-spy raw output ends inside a stack (recorded without --threads?): "
            f"{pending[-1][:80]!r}"
        )
    return out


def function_name(frame: str) -> str:
    """``Writer.write (arpz/channel/writer.py:103)`` -> ``Writer.write``."""
    return frame.partition(" (")[0]


def shares(
    raw: str, *, within: str | None = None, lines: bool = False
) -> tuple[int, dict[str, collections.Counter[str]]]:
    """(samples, {"thread": ..., "inclusive": ..., "self": ...}) of py-spy's raw output; with
    ``within``, of the stacks that pass through that function only (its share of itself is
    then 100 %); with ``lines``, a row per line of each function."""
    counters = {k: collections.Counter[str]() for k in ("thread", "inclusive", "self")}
    total = 0
    for thread, functions, n in stacks(raw, lines=lines):
        if within is not None and not any(function_name(f) == within for f in functions):
            continue
        total += n
        counters["thread"][thread] += n
        for function in set(functions):
            counters["inclusive"][function] += n
        if functions:
            counters["self"][functions[-1]] += n
    return total, counters


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("raw", type=Path, help="py-spy record --format raw output")
    ap.add_argument("--top", type=int, default=30)
    ap.add_argument(
        "--within",
        metavar="FUNCTION",
        help="only the stacks through this function (e.g. sense): shares of its time",
    )
    ap.add_argument("--lines", action="store_true", help="a row per line, not per function")
    args = ap.parse_args()
    try:
        total, counters = shares(args.raw.read_text(), within=args.within, lines=args.lines)
    except (OSError, ValueError) as exc:
        ap.error(str(exc))
    if total == 0:
        ap.error(f"no samples{f' through {args.within}' if args.within else ''} in {args.raw}")
    print(f"{total} samples" + (f" through {args.within}" if args.within else ""))
    for kind, counter in counters.items():
        print(f"--- by {kind}")
        for name, n in counter.most_common(args.top):
            print(f"{100 * n / total:5.1f} %  {name[:150]}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
