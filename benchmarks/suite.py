"""The curated suite, ``python -m benchmarks``: what to run before a change to the reliable
channel or the CEDDP, and which figures must not move.

Each entry (``benchmarks/entries.py``) measures arpz and its baseline (raw Zenoh, zenoh.ext
Advanced, a raw subscriber, CVXPY, ...) in the same run and yields a few named ratios. This
compares each ratio with its reference in the table of ``benchmarks/RESULTS.md`` (between
``BEGIN`` and ``END``; the references are read from there, never written in code) and prints one
table. A ratio that regressed by more than ``THRESHOLD`` (lower when higher is better, higher when
lower is better) has its entry measured a second time, and fails only if both measurements
regressed. A ratio marked ``info`` in the table (noisier than the threshold between two honest
runs on this host, with the reason) is printed, never failed. Exit code 1 if any ratio failed or
an entry could not run, 2 on a usage or table error.

    python -m benchmarks                  # every entry (about 5 min on a 2-core VM)
    python -m benchmarks --list           # the entries, their ratios and references
    python -m benchmarks --only fleet,lossy --json /tmp/suite.json
    python -m benchmarks --quick --only optimiser   # fewer repetitions: a smoke test
    python -m benchmarks --update-results # the run's ratios become RESULTS.md's references
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import platform
import re
import subprocess
import sys
import time
import traceback
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, replace
from datetime import date
from importlib import metadata
from pathlib import Path
from typing import Any, TextIO

from benchmarks.entries import ENTRIES
from benchmarks.measurement import Entry, Measurement

#: a ratio regressed when it moved the wrong way by more than this share of its reference
THRESHOLD = 0.15
RESULTS = Path(__file__).resolve().with_name("RESULTS.md")
ROOT = RESULTS.parents[1]
BEGIN = "<!-- suite: begin (read by benchmarks/suite.py) -->"
END = "<!-- suite: end -->"
HEADER = "| entry | ratio | reference | better | gate | measured |"
DIRECTIONS = ("higher", "lower")


class TableError(ValueError):
    """RESULTS.md's suite table is missing or malformed."""


@dataclass(frozen=True)
class Reference:
    """One row of RESULTS.md's suite table."""

    entry: str
    ratio: str
    value: float
    better: str
    #: None: the ratio gates (fails the suite); else why it is only informational
    info: str | None = None
    #: when and at which commit the reference was measured
    measured: str = ""

    def row(self) -> str:
        gate = "yes" if self.info is None else f"info: {self.info}"
        value = f"{self.value:#.3g}".rstrip(".")
        cells = [self.entry, self.ratio, f"{value}x", self.better, gate, self.measured]
        return "| " + " | ".join(cells) + " |"


@dataclass
class Verdict:
    """A ratio's outcome: its measurements (two when its entry was measured again)."""

    entry: str
    ratio: str
    better: str
    measured: list[float]
    reference: Reference | None
    status: str
    note: str = ""

    @property
    def failed(self) -> bool:
        return self.status in ("FAIL", "MISSING", "ERROR")


# ------------------------------------------------------------------------------ the comparison
def regressed(value: float, reference: Reference, threshold: float = THRESHOLD) -> bool:
    """Whether ``value`` moved the wrong way by more than ``threshold`` of the reference."""
    if value != value:  # NaN: nothing measured
        return True
    if reference.better == "higher":
        return value < reference.value * (1.0 - threshold)
    return value > reference.value * (1.0 + threshold)


def change(value: float, reference: Reference) -> float:
    """The relative change against the reference (+0.20: 20 % above it, whichever is better)."""
    return value / reference.value - 1.0 if reference.value else float("inf")


def needs_second(
    entry: Entry, first: Measurement, references: dict[tuple[str, str], Reference]
) -> list[str]:
    """The gating ratios of ``first`` that regressed against their references."""
    out = []
    for name, value in first.ratios.items():
        ref = references.get((entry.name, name))
        if ref is not None and ref.info is None and regressed(value, ref):
            out.append(name)
    return out


def verdicts(
    entry: Entry,
    first: Measurement,
    second: Measurement | None,
    references: dict[tuple[str, str], Reference],
) -> list[Verdict]:
    """One verdict a ratio of the entry (its declared ratios, then any other it measured)."""
    names = list(entry.ratios) + [n for n in first.ratios if n not in entry.ratios]
    out = []
    for name in names:
        ref = references.get((entry.name, name))
        better = entry.ratios.get(name, ref.better if ref else "higher")
        measured = [m.ratios[name] for m in (first, second) if m is not None and name in m.ratios]
        v = Verdict(entry.name, name, better, measured, ref, "pass")
        if not measured:
            v.status, v.note = "MISSING", "the entry did not measure it"
        elif ref is None:
            v.status, v.note = "new", "no reference in RESULTS.md"
        elif ref.info is not None:
            v.status = "info"
            if regressed(measured[-1], ref):
                v.note = f"beyond {THRESHOLD:.0%}, informational: {ref.info}"
        elif regressed(measured[0], ref):
            if len(measured) > 1 and regressed(measured[1], ref):
                v.status, v.note = "FAIL", "regressed in both measurements"
            elif len(measured) > 1:
                v.status, v.note = "pass", "regressed in the 1st measurement, not in the 2nd"
            else:
                v.status, v.note = "FAIL", "regressed; no second measurement"
        out.append(v)
    return out


def error_verdicts(
    entry: Entry, references: dict[tuple[str, str], Reference], why: str
) -> list[Verdict]:
    return [
        Verdict(entry.name, name, better, [], references.get((entry.name, name)), "ERROR", why)
        for name, better in entry.ratios.items()
    ]


# ------------------------------------------------------------------------ RESULTS.md's table
def _cells(line: str) -> list[str]:
    return [cell.strip() for cell in line.strip().strip("|").split("|")]


def table_bounds(lines: Sequence[str]) -> tuple[int, int]:
    """The indexes of the BEGIN and END lines."""
    try:
        begin = next(i for i, line in enumerate(lines) if line.strip() == BEGIN)
        end = next(i for i, line in enumerate(lines) if i > begin and line.strip() == END)
    except StopIteration:
        raise TableError(f"RESULTS.md has no suite table between {BEGIN!r} and {END!r}") from None
    return begin, end


def parse_references(text: str) -> dict[tuple[str, str], Reference]:
    """The suite table of RESULTS.md's text, by (entry, ratio)."""
    lines = text.splitlines()
    begin, end = table_bounds(lines)
    refs: dict[tuple[str, str], Reference] = {}
    header_seen = False
    for number, line in enumerate(lines[begin + 1 : end], start=begin + 2):
        if not line.startswith("|"):
            continue
        cells = _cells(line)
        if cells == _cells(HEADER):
            header_seen = True
            continue
        if all(set(cell) <= set("-: ") for cell in cells):
            continue
        if len(cells) != len(_cells(HEADER)):
            raise TableError(f"RESULTS.md line {number}: {len(cells)} cells, expected 6")
        entry, ratio, value, better, gate, measured = cells
        found = re.fullmatch(r"([0-9.eE+-]+)x?", value)
        if found is None:
            raise TableError(f"RESULTS.md line {number}: reference {value!r} is not a ratio")
        if better not in DIRECTIONS:
            raise TableError(f"RESULTS.md line {number}: better {better!r}: higher or lower")
        if gate != "yes" and not gate.startswith("info:"):
            raise TableError(f"RESULTS.md line {number}: gate {gate!r}: yes or info: REASON")
        info = None if gate == "yes" else gate.removeprefix("info:").strip()
        if (entry, ratio) in refs:
            raise TableError(f"RESULTS.md line {number}: {entry} / {ratio} twice")
        refs[(entry, ratio)] = Reference(
            entry, ratio, float(found.group(1)), better, info, measured
        )
    if not header_seen:
        raise TableError(f"RESULTS.md's suite table has no header row {HEADER!r}")
    return refs


def updated_results(
    text: str, measured: Iterable[Verdict], stamp: str, run_line: str | None
) -> str:
    """RESULTS.md with the references of the measured ratios replaced by their last
    measurement (new ratios appended as gating rows), their ``measured`` cell set to ``stamp``,
    and (a full run) the line starting "Last full run:" replaced by ``run_line``."""
    lines = text.splitlines()
    begin, end = table_bounds(lines)
    refs = parse_references(text)
    for v in measured:
        if not v.measured or v.status == "ERROR":
            continue
        old = refs.get((v.entry, v.ratio))
        base = old or Reference(v.entry, v.ratio, 0.0, v.better)
        new_ref = replace(base, value=v.measured[-1], measured=stamp)
        if old is not None:
            refs[(v.entry, v.ratio)] = new_ref
            continue
        # a new ratio goes after its entry's last row (at the end for a new entry)
        keys = list(refs)
        at = max((i + 1 for i, key in enumerate(keys) if key[0] == v.entry), default=len(keys))
        keys.insert(at, (v.entry, v.ratio))
        refs = {key: new_ref if key == (v.entry, v.ratio) else refs[key] for key in keys}
    body = [line for line in lines[begin + 1 : end] if not line.startswith("|")]
    if run_line is not None:
        body = [run_line if line.startswith("Last full run:") else line for line in body]
    while body and not body[-1].strip():
        body.pop()
    table = [HEADER, "|---|---|---:|---|---|---|", *(ref.row() for ref in refs.values())]
    new = [*lines[: begin + 1], *body, "", *table, *lines[end:]]
    return "\n".join(new) + ("\n" if text.endswith("\n") else "")


# ------------------------------------------------------------------------------- printing
def _ratio(value: float) -> str:
    if value >= 100:
        return f"{value:.0f}x"
    return f"{value:.1f}x" if value >= 10 else f"{value:.2f}x"


def result_table(all_verdicts: Sequence[Verdict]) -> str:
    rows = [
        "| entry | ratio | measured | RESULTS.md | better | change | verdict |",
        "|---|---|---:|---:|---|---:|---|",
    ]
    for v in all_verdicts:
        measured = ", ".join(_ratio(x) for x in v.measured) or "-"
        ref = _ratio(v.reference.value) if v.reference else "-"
        moved = (
            ", ".join(f"{change(x, v.reference):+.0%}" for x in v.measured)
            if v.reference and v.measured
            else "-"
        )
        verdict = v.status + (f" ({v.note})" if v.note else "")
        rows.append(
            f"| {v.entry} | {v.ratio} | {measured} | {ref} | {v.better} | {moved} | {verdict} |"
        )
    return "\n".join(rows)


def _clock(seconds: float) -> str:
    minutes, secs = divmod(round(seconds), 60)
    return f"{minutes}:{secs:02d}"


def machine() -> str:
    """The host in one line: CPU model, cores, Python, Zenoh."""
    model = "unknown CPU"
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    try:
        zenoh = metadata.version("eclipse-zenoh")
    except metadata.PackageNotFoundError:
        zenoh = "?"
    return (
        f"{os.cpu_count()} cores, {model}, Linux {platform.release()}, "
        f"Python {platform.python_version()}, eclipse-zenoh {zenoh}"
    )


def commit() -> str:
    """HEAD's short hash, "+changes" when arpz/ or benchmarks/ differ from it."""

    def git(*args: str) -> str:
        done = subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True)
        return done.stdout.strip() if done.returncode == 0 else ""

    head = git("rev-parse", "--short", "HEAD") or "unknown commit"
    dirty = git("status", "--porcelain", "--", "arpz", "benchmarks")
    return head + (" +changes" if dirty else "")


# ------------------------------------------------------------------------------- the run
@dataclass
class EntryRun:
    entry: str
    seconds: float
    measurements: list[dict[str, float]]
    details: list[str]
    error: str | None = None


def run_entry(
    entry: Entry,
    references: dict[tuple[str, str], Reference],
    quick: bool,
    progress: Callable[[str], object],
    verbose: bool = False,
) -> tuple[EntryRun, list[Verdict]]:
    """Measure the entry (twice if a gating ratio regressed) and judge its ratios."""
    started = time.monotonic()
    measurements: list[Measurement] = []
    for attempt in (1, 2):
        captured = io.StringIO()
        sink: TextIO = sys.stderr if verbose else captured
        try:
            with contextlib.redirect_stdout(sink), contextlib.redirect_stderr(sink):
                measurements.append(entry.run(quick))
        except Exception as exc:  # an entry that cannot run fails the suite, the rest runs on
            tail = "\n".join(captured.getvalue().splitlines()[-30:])
            why = f"{type(exc).__name__}: {exc}"
            progress(f"  {entry.name}: ERROR {why}\n{tail}\n{traceback.format_exc()}")
            run = EntryRun(entry.name, time.monotonic() - started, [], [], why)
            run.measurements = [m.ratios for m in measurements]
            return run, error_verdicts(entry, references, why)
        if attempt == 2:
            break
        again = needs_second(entry, measurements[0], references)
        if not again:
            break
        listed = ", ".join(
            f"{name} {_ratio(measurements[0].ratios[name])} against "
            f"{_ratio(references[(entry.name, name)].value)}"
            for name in again
        )
        progress(f"  {entry.name}: regressed beyond {THRESHOLD:.0%} ({listed}): measuring again")
    first, second = measurements[0], (measurements[1] if len(measurements) > 1 else None)
    details = [line for m in measurements for line in m.details]
    run = EntryRun(
        entry.name, time.monotonic() - started, [m.ratios for m in measurements], details
    )
    return run, verdicts(entry, first, second, references)


def check_directions(
    entries: Sequence[Entry], references: dict[tuple[str, str], Reference]
) -> list[str]:
    """Where RESULTS.md and an entry disagree on which way a ratio is better."""
    return [
        f"{e.name} / {name}: RESULTS.md says {ref.better}, the entry {better}"
        for e in entries
        for name, better in e.ratios.items()
        if (ref := references.get((e.name, name))) is not None and ref.better != better
    ]


def select(entries: Sequence[Entry], only: Sequence[str]) -> list[Entry]:
    names = [n for text in only for n in text.split(",") if n]
    if not names:
        return list(entries)
    known = {e.name: e for e in entries}
    unknown = [n for n in names if n not in known]
    if unknown:
        raise SystemExit(
            f"unknown entry {', '.join(unknown)}; the entries: {', '.join(known)} (--list)"
        )
    return [known[n] for n in dict.fromkeys(names)]


def list_entries(entries: Sequence[Entry], references: dict[tuple[str, str], Reference]) -> str:
    lines = []
    for e in entries:
        lines.append(f"{e.name} (about {e.seconds:.0f} s): {e.what}")
        for name, better in e.ratios.items():
            ref = references.get((e.name, name))
            figure = "no reference" if ref is None else _ratio(ref.value)
            gate = "" if ref is None or ref.info is None else f", info: {ref.info}"
            lines.append(f"    {name}: {figure} ({better} is better{gate})")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None, entries: Sequence[Entry] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m benchmarks",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("--only", action="append", default=[], metavar="NAME[,NAME...]")
    ap.add_argument("--list", action="store_true", help="the entries and their references")
    ap.add_argument("--quick", action="store_true", help="fewer repetitions (a smoke test)")
    ap.add_argument("--json", type=Path, metavar="PATH", help="write the run's figures here")
    ap.add_argument("--results", type=Path, default=RESULTS, help="the reference table's file")
    ap.add_argument(
        "--update-results",
        action="store_true",
        help="write the run's ratios into the table as the new references",
    )
    ap.add_argument("--verbose", action="store_true", help="show the entries' own output")
    args = ap.parse_args(argv)
    if entries is None:
        entries = ENTRIES
    text = args.results.read_text(encoding="utf-8")
    try:
        references = parse_references(text)
    except TableError as exc:
        print(f"python -m benchmarks: {exc}", file=sys.stderr)
        return 2
    mismatched = check_directions(entries, references)
    if mismatched:
        print("python -m benchmarks: " + "; ".join(mismatched), file=sys.stderr)
        return 2
    chosen = select(entries, args.only)
    if args.list:
        print(list_entries(chosen, references))
        return 0
    if args.update_results and args.quick:
        print("python -m benchmarks: --quick figures are not references", file=sys.stderr)
        return 2

    # every process an entry starts runs this checkout's arpz, not an installed one (the fleet
    # starts its CEDDP and workers in a temporary directory)
    path = os.environ.get("PYTHONPATH")
    os.environ["PYTHONPATH"] = str(ROOT) + (os.pathsep + path if path else "")
    err = sys.stderr
    t0 = time.monotonic()

    def progress(line: str) -> None:
        print(f"[{_clock(time.monotonic() - t0)}] {line}", file=err, flush=True)

    entries_text = f"{len(chosen)} entr{'y' if len(chosen) == 1 else 'ies'}"
    progress(
        f"suite: {entries_text}{' (quick)' if args.quick else ''}, against "
        f"{args.results.name}; {machine()}; {commit()}"
    )
    runs: list[EntryRun] = []
    all_verdicts: list[Verdict] = []
    for i, entry in enumerate(chosen, start=1):
        progress(f"{entry.name} ({i}/{len(chosen)}): started")
        run, entry_verdicts = run_entry(entry, references, args.quick, progress, args.verbose)
        runs.append(run)
        all_verdicts += entry_verdicts
        shown = "; ".join(
            f"{v.ratio} {', '.join(_ratio(x) for x in v.measured)}"
            for v in entry_verdicts
            if v.measured
        )
        state = "ERROR" if run.error else "done"
        progress(f"{entry.name} ({i}/{len(chosen)}): {state} in {run.seconds:.0f} s: {shown}")
    elapsed = time.monotonic() - t0
    failed = [v for v in all_verdicts if v.failed]
    twice = [r.entry for r in runs if len(r.measurements) > 1]
    print(result_table(all_verdicts))
    print()
    for run in runs:
        for line in run.details:
            print(f"- {run.entry}: {line}")
    print()
    print(
        f"A ratio fails when it regressed by more than {THRESHOLD:.0%} against RESULTS.md in two "
        f"measurements of its entry; measured twice: {', '.join(twice) or 'none'}."
        + (" --quick: fewer repetitions, noisier figures." if args.quick else "")
    )
    counts = {s: sum(v.status == s for v in all_verdicts) for s in ("pass", "info", "new")}
    print(
        f"suite: {entries_text} in {elapsed / 60:.1f} min ({_clock(elapsed)}): "
        f"{counts['pass']} pass, {len(failed)} failed, {counts['info']} informational, "
        f"{counts['new']} new; {'FAILED' if failed else 'passed'}"
    )
    if args.json is not None:
        doc: dict[str, Any] = {
            "date": date.today().isoformat(),
            "commit": commit(),
            "machine": machine(),
            "quick": args.quick,
            "elapsed_s": round(elapsed, 1),
            "threshold": THRESHOLD,
            "passed": not failed,
            "entries": [asdict(r) for r in runs],
            "ratios": [
                {**asdict(v), "reference": v.reference.value if v.reference else None}
                for v in all_verdicts
            ],
        }
        args.json.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    if args.update_results:
        stamp = f"{date.today().isoformat()}, {commit()}"
        full = len(chosen) == len(entries)
        run_line = (
            f"Last full run: {stamp}, {elapsed // 60:.0f} min {elapsed % 60:.0f} s, on {machine()}."
            if full
            else None
        )
        new_text = updated_results(text, all_verdicts, stamp, run_line)
        args.results.write_text(new_text, encoding="utf-8")
        print(f"wrote the run's ratios into {args.results}")
    return 1 if failed else 0
