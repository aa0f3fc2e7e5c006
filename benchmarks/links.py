"""Every robot link type on a lossy radio: tcp, tls, udp and quic through the kernel lab.

For each loss (0, 5 and 15 % each way: the lab's ``loss-P`` profile, nftables dropping frames
on the receiving end of each direction, as a radio) and each link (``tcp``; ``tls`` and
``quic`` with the fleet's mutual TLS and access control, the certificates and Zenoh files of
``deploy/tls/make_fleet_certs.py``, as docs/deploy.md sets up; ``udp``, where arpz's reliable
channel does the recovering), this runs the real CEDDP and robots in the lab
(``arpz.lab.run_fleet_in_lab``: the configs of ``python -m arpz lab run``, i.e. of
``python -m arpz demo``: the paper's machine1 / machine2 sensor sets at 50 Hz with the local
cache, cache control, the QoS optimiser at Rmax 500 Hz, RELIABLE KEEP_LAST, robot1's Hello
relayed by robot2 at 10 Hz) for a fixed window, and prints one table, read from the CEDDP's
summary.json and from /proc:

- sensor latency p50 / p99 (the worst robot's, source stamp to CEDDP);
- Hello round trip p99 (robot1 -> CEDDP -> robot2 -> CEDDP -> robot1) and Hellos lost / late
  (not back within 2 s) of those sent;
- commands expired (downlink messages the robots dropped past their lifespan, Hello hops
  included) and watchdog stops;
- samples lost / received (CEDDP side, whole run), samples/s (received over the CEDDP's run);
- wire kB/s: bytes the robots' interfaces sent and received during the window (both robots,
  retransmissions and the protocol's own overhead included);
- CPU of a robot (mean of the robots) and of the CEDDP, % of one core during the window;
- other cores: what the rest of the host used meanwhile (its busy CPU, stolen time included,
  minus the fleet's), marked ``!`` from 0.25 cores: on a shared 2-core machine a busy
  neighbour moves the tail as much as the link does, so such a cell is worth running again;
- reconciled: every robot's final report arrived and its counts add up (``check_summary``),
  the downlink reconciles, every incarnation reconciles.

Then the ratios against the ``tcp`` row at the same loss, measured in the same run (loss is the
outer loop, so the rows compared ran minutes apart at most). A cell that fails (a link that does
not come up, a process that exits) is a row marked FAILED with why; the run goes on. The table
is also written as ``links.csv`` and ``links.json`` under ``--out``, beside each cell's configs,
logs, summary.json and lab timeline (``cells/LINK-lossP/``).

Needs root, ``nft`` and ``ip`` (docs/netem.md, "The kernel lab"). Twelve cells of 30 s take
about 6.5 minutes on a 2-core machine (390-407 s measured):

    python benchmarks/links.py --out /tmp/links
    python benchmarks/links.py --links tcp quic --loss 15 --duration 20
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from arpz.core.errors import ArpzError  # noqa: E402
from arpz.experiment.results import downlink  # noqa: E402
from arpz.lab import (  # noqa: E402
    Lab,
    LabRunOptions,
    LabUnavailable,
    Timeline,
    check_available,
    lab_spec,
    loss,
    run_fleet_in_lab,
)
from arpz.lab.fleet import LINKS  # noqa: E402
from arpz.lab.timeline import TIMELINE_FILE, Entry  # noqa: E402
from arpz.tools.demo import DemoOptions  # noqa: E402

#: the order of the rows at each loss: the baseline first
DEFAULT_LINKS = ("tcp", "tls", "udp", "quic")
DEFAULT_LOSSES = (0.0, 5.0, 15.0)
BASELINE = "tcp"
#: seconds between two readings of the processes' CPU and the robots' interface counters
SAMPLE_EVERY_S = 0.5
CLOCK_TICKS = os.sysconf("SC_CLK_TCK")
#: CPU (cores) used by other processes than the fleet's during a window that marks the cell
#: with "!": its tail may be the host's, not the link's
BUSY_CORES = 0.25
COLUMNS = (
    "link",
    "loss_pct",
    "status",
    "error",
    "latency_ms_p50",
    "latency_ms_p99",
    "hello_ms_p99",
    "hello_sent",
    "hello_lost",
    "hello_late",
    "commands_expired",
    "watchdog_stops",
    "samples_sent",
    "samples_received",
    "samples_lost",
    "samples_per_s",
    "wire_kb_per_s",
    "robot_cpu_pct",
    "ceddp_cpu_pct",
    "window_s",
    "host_other_cores",
    "host_steal_cores",
    "reconciled",
    "not_reconciled",
    "wall_s",
    "workdir",
)


# ------------------------------------------------------------------- the processes, from /proc


@dataclass
class Reading:
    mono: float
    #: CPU seconds (user + system) of each fleet process, by role: "ceddp", "robot1" ...
    cpu_s: dict[str, float] = field(default_factory=dict)
    #: bytes sent + received on each robot's own interface (its network namespace's)
    wire_bytes: dict[str, int] = field(default_factory=dict)
    #: the whole host's busy CPU seconds (every core, stolen time included) and stolen ones
    host_busy_s: float = 0.0
    host_steal_s: float = 0.0


def _host_cpu() -> tuple[float, float]:
    """(busy, stolen) CPU seconds of the host since boot, every core (/proc/stat)."""
    try:
        first = Path("/proc/stat").read_text().splitlines()[0].split()
    except OSError:
        return 0.0, 0.0
    # cpu user nice system idle iowait irq softirq steal (guest time is inside user)
    ticks = [int(v) for v in first[1:9]]
    busy = sum(ticks) - ticks[3] - ticks[4]
    return busy / CLOCK_TICKS, ticks[7] / CLOCK_TICKS


def _stat(pid: str) -> tuple[int, float] | None:
    """(parent pid, CPU seconds) of ``pid`` (None: gone)."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text[text.rindex(")") + 2 :].split()  # after "pid (comm) "
    return int(fields[1]), (int(fields[11]) + int(fields[12])) / CLOCK_TICKS


def _role(pid: str) -> str | None:
    """The role of a child ("ceddp", "robotN"), or None: not a fleet process."""
    try:
        args = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return None
    words = [a.decode(errors="replace") for a in args]
    if "arpz.ceddp" in words:
        return "ceddp"
    if "arpz.robot" in words and "--config" in words[:-1]:
        return Path(words[words.index("--config") + 1]).stem
    return None


def _wire_bytes(pid: str) -> int | None:
    """rx + tx bytes on the interfaces of ``pid``'s network namespace (loopback aside)."""
    try:
        lines = Path(f"/proc/{pid}/net/dev").read_text().splitlines()[2:]
    except OSError:
        return None
    total = 0
    for line in lines:
        name, _, counters = line.partition(":")
        if name.strip() != "lo":
            values = counters.split()
            total += int(values[0]) + int(values[8])
    return total


class Sampler:
    """Reads the CPU of this process's fleet children (the lab's ``ip netns exec`` execs the
    Python process in place, so they are direct children) and the robots' interface counters
    every ``SAMPLE_EVERY_S`` on a thread."""

    def __init__(self) -> None:
        self.readings: list[Reading] = []
        self._roles: dict[str, str | None] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="links-sampler", daemon=True)

    def _read(self) -> Reading:
        me = os.getpid()
        reading = Reading(time.monotonic())
        reading.host_busy_s, reading.host_steal_s = _host_cpu()
        for pid in (p for p in os.listdir("/proc") if p.isdigit()):
            stat = _stat(pid)
            if stat is None or stat[0] != me:
                continue
            if pid not in self._roles:
                self._roles[pid] = _role(pid)
            role = self._roles[pid]
            if role is None:
                continue
            reading.cpu_s[role] = stat[1]
            if role != "ceddp" and (wire := _wire_bytes(pid)) is not None:
                reading.wire_bytes[role] = wire
        return reading

    def _run(self) -> None:
        while not self._stop.wait(SAMPLE_EVERY_S):
            self.readings.append(self._read())

    def __enter__(self) -> Sampler:
        self._thread.start()
        return self

    def __exit__(self, *_: object) -> None:
        self._stop.set()
        self._thread.join(timeout=5)

    def window(self, start: float, end: float) -> tuple[Reading, Reading] | None:
        """The first reading at or after ``start`` and the last at or before ``end``."""
        inside = [r for r in self.readings if start <= r.mono <= end]
        return (inside[0], inside[-1]) if len(inside) >= 2 else None


# ------------------------------------------------------------------------------------- a cell


def _window(entries: list[Entry]) -> tuple[float, float] | None:
    """The measured window on the monotonic clock: from the profiles' start (the fleet is up)
    to the links made clean for the shutdown."""
    start = next((e["mono"] for e in entries if e["event"] == "profile"), None)
    end = next(
        (
            e["mono"]
            for e in entries
            if e["event"] == "link" and str(e.get("cause", "")).startswith("end of the run")
        ),
        None,
    )
    return (start, end) if start is not None and end is not None else None


def _max(values: list[Any]) -> float | None:
    present = [float(v) for v in values if v is not None]
    return max(present) if present else None


def _reconciled(summary: dict[str, Any], problems: list[str]) -> list[str]:
    """What does not add up (empty: reconciled)."""
    robots: dict[str, Any] = summary.get("robots") or {}
    why = list(problems)
    flow = downlink(robots)
    if flow["downlink_reconciled"] != "yes":
        why.append(f"downlink {flow['downlink_reconciled']}: {flow['downlink_unreconciled']}")
    for name, row in sorted(robots.items()):
        for guid, incarnation in (row.get("incarnations") or {}).items():
            if incarnation.get("reconciled") is not True:
                why.append(f"{name} incarnation {guid}: {incarnation}")
    return why


def row_of(
    summary: dict[str, Any], problems: list[str], measured: tuple[Reading, Reading] | None
) -> dict[str, Any]:
    """The table's figures of a finished cell."""
    robots: dict[str, Any] = summary.get("robots") or {}
    rows = list(robots.values())
    hello = (robots.get("robot1") or {}).get("hello") or {}
    received = sum(int(r.get("received") or 0) for r in rows)
    duration = float(summary.get("duration_s") or 0.0)
    row: dict[str, Any] = {
        "status": "ok",
        "latency_ms_p50": _max([r.get("latency_ms_p50") for r in rows]),
        "latency_ms_p99": _max([r.get("latency_ms_p99") for r in rows]),
        "hello_ms_p99": hello.get("rtt_ms_p99"),
        "hello_sent": hello.get("sent"),
        "hello_lost": hello.get("lost"),
        "hello_late": hello.get("late"),
        "commands_expired": sum(int(r.get("commands_expired") or 0) for r in rows),
        "watchdog_stops": sum(sum((r.get("watchdog_stops") or {}).values()) for r in rows),
        "samples_sent": sum(int(r.get("sent") or 0) for r in rows),
        "samples_received": received,
        "samples_lost": sum(int(r.get("lost") or 0) for r in rows),
        "samples_per_s": received / duration if duration else None,
    }
    if measured is not None:
        first, last = measured
        seconds = last.mono - first.mono
        robot_names = [n for n in last.cpu_s if n != "ceddp" and n in first.cpu_s]
        cpu = {n: 100.0 * (last.cpu_s[n] - first.cpu_s[n]) / seconds for n in robot_names}
        wire = sum(
            last.wire_bytes[n] - first.wire_bytes[n]
            for n in last.wire_bytes
            if n in first.wire_bytes
        )
        row["window_s"] = seconds
        fleet = sum(last.cpu_s[n] - first.cpu_s[n] for n in last.cpu_s if n in first.cpu_s)
        busy = last.host_busy_s - first.host_busy_s
        row["host_other_cores"] = max(0.0, busy - fleet) / seconds
        row["host_steal_cores"] = (last.host_steal_s - first.host_steal_s) / seconds
        row["robot_cpu_pct"] = sum(cpu.values()) / len(cpu) if cpu else None
        if "ceddp" in first.cpu_s and "ceddp" in last.cpu_s:
            row["ceddp_cpu_pct"] = 100.0 * (last.cpu_s["ceddp"] - first.cpu_s["ceddp"]) / seconds
        row["wire_kb_per_s"] = wire / seconds / 1000.0
    why = _reconciled(summary, problems)
    row["reconciled"] = "no" if why else "yes"
    row["not_reconciled"] = "; ".join(why)
    return row


class _Prefixed(io.StringIO):
    """The lab's progress lines, each prefixed with the cell it is about."""

    def __init__(self, prefix: str) -> None:
        super().__init__()
        self.prefix = prefix
        self._pending = ""

    def write(self, text: str) -> int:
        self._pending += text
        while "\n" in self._pending:
            line, self._pending = self._pending.split("\n", 1)
            if line.strip():
                print(f"{self.prefix} {line}", file=sys.stderr, flush=True)
        return len(text)


def run_cell(
    link: str,
    loss_pct: float,
    workdir: Path,
    *,
    robots: int,
    duration_s: float,
    history: str,
    seed: int,
    prefix: str,
) -> dict[str, Any]:
    """One link at one loss in a lab of its own; a failure is a row with ``error``."""
    started = time.monotonic()
    cell: dict[str, Any] = {"link": link, "loss_pct": loss_pct, "workdir": str(workdir)}
    options = LabRunOptions(
        robots=robots,
        link=link,
        duration_s=duration_s,
        seed=seed,
        demo=DemoOptions(rate_hz=50.0, rmax_hz=500.0, history=history),
    )
    workdir.mkdir(parents=True, exist_ok=True)
    try:
        with (
            Lab.create(options.robot_names, timeline=Timeline(workdir / TIMELINE_FILE)) as lab,
            Sampler() as sampler,
        ):
            result = run_fleet_in_lab(
                lab,
                lab_spec(options, lab, workdir),
                workdir,
                profiles=dict.fromkeys(options.robot_names, loss(loss_pct)),
                duration_s=duration_s,
                seed=seed,
                progress=_Prefixed(prefix),
            )
            span = _window(lab.timeline.entries)
            measured = sampler.window(*span) if span else None
        cell |= row_of(result.summary, result.problems, measured)
    except LabUnavailable:
        raise
    except (ArpzError, OSError, ValueError) as exc:
        cell |= {"status": "failed", "error": str(exc).strip()}
    cell["wall_s"] = time.monotonic() - started
    return cell


# ----------------------------------------------------------------------------------- the table


def _num(value: Any, digits: int = 1) -> str:
    if value is None or value == "":
        return "-"
    if isinstance(value, float):
        return f"{value:,.{digits}f}".replace(",", " ")
    return f"{value:,}".replace(",", " ")


HEADERS = (
    "link",
    "loss",
    "lat p50 ms",
    "lat p99 ms",
    "Hello p99 ms",
    "Hello lost/late/sent",
    "cmd expired",
    "wd stops",
    "samples lost/received",
    "samples/s",
    "wire kB/s",
    "CPU robot %",
    "CPU CEDDP %",
    "other cores",
    "reconciled",
)


def _busy(row: dict[str, Any]) -> bool:
    """The host was busy with something else than the fleet during the cell's window."""
    return float(row.get("host_other_cores") or 0.0) >= BUSY_CORES


def table_rows(rows: list[dict[str, Any]]) -> list[list[str]]:
    out = []
    for r in rows:
        head = [r["link"], f"{r['loss_pct']:g} %"]
        if r["status"] != "ok":
            first = str(r.get("error") or "").splitlines()[0] if r.get("error") else "?"
            out.append([*head, f"FAILED: {first}"])
            continue
        out.append(
            [
                *head,
                _num(r["latency_ms_p50"]),
                _num(r["latency_ms_p99"]),
                _num(r["hello_ms_p99"]),
                f"{_num(r['hello_lost'])}/{_num(r['hello_late'])}/{_num(r['hello_sent'])}",
                _num(r["commands_expired"]),
                _num(r["watchdog_stops"]),
                f"{_num(r['samples_lost'])}/{_num(r['samples_received'])}",
                _num(r["samples_per_s"]),
                _num(r.get("wire_kb_per_s")),
                _num(r.get("robot_cpu_pct")),
                _num(r.get("ceddp_cpu_pct")),
                _num(r.get("host_other_cores"), 2) + ("!" if _busy(r) else ""),
                r["reconciled"],
            ]
        )
    return out


def format_table(headers: tuple[str, ...], rows: list[list[str]]) -> str:
    widths = [len(h) for h in headers]
    for row in rows:
        if len(row) == len(headers):
            widths = [max(w, len(c)) for w, c in zip(widths, row, strict=True)]
    lines = ["  ".join(h.rjust(w) for h, w in zip(headers, widths, strict=True))]
    for row in rows:
        if len(row) == len(headers):
            lines.append("  ".join(c.rjust(w) for c, w in zip(row, widths, strict=True)))
        else:  # a failed cell: its reason after link and loss
            lines.append(
                "  ".join(c.rjust(w) for c, w in zip(row[:2], widths, strict=False)) + "  " + row[2]
            )
    return "\n".join(lines)


RATIOS = (
    ("lat p50", "latency_ms_p50"),
    ("lat p99", "latency_ms_p99"),
    ("Hello p99", "hello_ms_p99"),
    ("wire kB/s", "wire_kb_per_s"),
    ("CPU robot", "robot_cpu_pct"),
    ("CPU CEDDP", "ceddp_cpu_pct"),
)


def ratio_rows(rows: list[dict[str, Any]]) -> list[list[str]]:
    """Each ok row against the ok ``tcp`` row at the same loss (x: this / tcp's)."""
    base = {r["loss_pct"]: r for r in rows if r["link"] == BASELINE and r["status"] == "ok"}
    out = []
    for r in rows:
        b = base.get(r["loss_pct"])
        if r["link"] == BASELINE or r["status"] != "ok" or b is None:
            continue
        cells = [r["link"], f"{r['loss_pct']:g} %"]
        for _, key in RATIOS:
            mine, theirs = r.get(key), b.get(key)
            if mine is None or theirs is None or theirs <= 0 or mine < 0:
                cells.append("-")  # a negative p50: clock offsets, no ratio to take
            else:
                cells.append(f"{mine / theirs:.2f}x")
        out.append(cells)
    return out


def write_outputs(out: Path, rows: list[dict[str, Any]], machine: dict[str, Any]) -> None:
    with (out / "links.csv").open("w", newline="", encoding="utf-8") as handle:
        writer = csv.DictWriter(handle, fieldnames=COLUMNS, extrasaction="ignore")
        writer.writeheader()
        for row in rows:
            writer.writerow({k: "" if row.get(k) is None else row.get(k) for k in COLUMNS})
    (out / "links.json").write_text(
        json.dumps({"machine": machine, "rows": rows}, indent=2) + "\n", encoding="utf-8"
    )


def machine() -> dict[str, Any]:
    """What the figures were measured on."""
    model = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass

    def git(*args: str) -> str:
        try:
            done = subprocess.run(
                ["git", "-C", str(ROOT), *args], capture_output=True, text=True, check=False
            )
        except OSError:
            return ""
        return done.stdout.strip()

    commit = git("rev-parse", "--short", "HEAD")
    if commit and git("status", "--porcelain", "--untracked-files=no", "--", "arpz"):
        commit += " with uncommitted changes in arpz/"
    try:
        zenoh_version = metadata.version("eclipse-zenoh")
    except metadata.PackageNotFoundError:
        zenoh_version = ""
    return {
        "cpu": model,
        "cores": os.cpu_count(),
        "kernel": platform.release(),
        "python": platform.python_version(),
        "zenoh": zenoh_version,
        "commit": commit,
        "date": time.strftime("%Y-%m-%d %H:%M"),
    }


@contextmanager
def _elapsed() -> Iterator[Any]:
    started = time.monotonic()
    yield lambda: time.monotonic() - started


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0] if __doc__ else None,
        epilog="docs/netem.md, 'The kernel lab'; benchmarks/RESULTS.md has the figures",
    )
    parser.add_argument("--links", nargs="+", choices=LINKS, default=list(DEFAULT_LINKS))
    parser.add_argument(
        "--loss", nargs="+", type=float, default=list(DEFAULT_LOSSES), help="% each way"
    )
    parser.add_argument("--duration", type=float, default=30.0, help="seconds of loss per cell")
    parser.add_argument("--robots", type=int, default=2)
    parser.add_argument("--history", choices=["keep_last", "keep_all"], default="keep_last")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, help="links.csv, links.json, cells/ (default: temp)")
    args = parser.parse_args(argv)
    try:
        check_available()
    except LabUnavailable as exc:
        print(f"links: the kernel lab cannot run here: {exc}", file=sys.stderr)
        return 2
    out: Path = args.out or Path(tempfile.mkdtemp(prefix="arpz-links-"))
    out.mkdir(parents=True, exist_ok=True)
    # the baseline first at each loss, whatever order --links gave
    links = sorted(dict.fromkeys(args.links), key=lambda link: link != BASELINE)
    cells = [(link, pct) for pct in args.loss for link in links]
    about = machine()
    rows: list[dict[str, Any]] = []
    with _elapsed() as elapsed:
        for index, (link, pct) in enumerate(cells, 1):
            prefix = f"[{index}/{len(cells)} {link} {pct:g} %]"
            print(f"{prefix} starting ({elapsed():.0f} s into the run)", file=sys.stderr)
            row = run_cell(
                link,
                pct,
                out / "cells" / f"{link}-loss{pct:g}",
                robots=args.robots,
                duration_s=args.duration,
                history=args.history,
                seed=args.seed,
                prefix=prefix,
            )
            rows.append(row)
            done = (
                f"p99 {_num(row['latency_ms_p99'])} ms, Hello p99 {_num(row['hello_ms_p99'])} ms, "
                f"reconciled {row['reconciled']}"
                if row["status"] == "ok"
                else f"FAILED: {str(row['error']).splitlines()[0] if row['error'] else '?'}"
            )
            print(f"{prefix} done in {row['wall_s']:.0f} s: {done}", file=sys.stderr, flush=True)
            write_outputs(out, rows, about)
        total = elapsed()
    print(
        f"\nLink types on a lossy radio (kernel lab): {args.robots} robots (machine1/machine2 "
        f"sets, 50 Hz, local cache, QoS Rmax 500 Hz, RELIABLE {args.history.upper()}, Hello "
        f"10 Hz), {args.duration:g} s of loss each way per cell; {len(cells)} cells in "
        f"{total:.0f} s"
    )
    print(
        f"machine: {about['cpu']}, {about['cores']} cores, kernel {about['kernel']}, Python "
        f"{about['python']}, zenoh {about['zenoh']}, commit {about['commit']}, {about['date']}\n"
    )
    print(format_table(HEADERS, table_rows(rows)))
    ratios = ratio_rows(rows)
    if ratios:
        print(f"\nagainst {BASELINE} at the same loss (this / {BASELINE}'s):")
        print(format_table(("link", "loss", *(name for name, _ in RATIOS)), ratios))
    if any(_busy(r) for r in rows):
        print(
            f"! other processes than the fleet used >= {BUSY_CORES} cores of the host during "
            "the window (other cores: the host's busy CPU, stolen time included, minus the "
            "fleet's): that cell's tail may be the host's, not the link's; run it again"
        )
    for r in rows:
        if r["status"] == "ok" and r["reconciled"] != "yes":
            print(f"not reconciled: {r['link']} {r['loss_pct']:g} %: {r['not_reconciled']}")
        if r["status"] != "ok":
            print(f"failed: {r['link']} {r['loss_pct']:g} %: {r['error']}")
    print(f"\n{out / 'links.csv'}, {out / 'links.json'}; each cell's logs under {out / 'cells'}")
    return 0 if all(r["status"] == "ok" for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
