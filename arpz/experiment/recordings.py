"""One ``.rrd`` with every run: the CEDDP of each cell writes its own recording, and
``rerun rrd merge`` puts them side by side in ``DIR/all_runs.rrd`` (one recording per cell).

Each cell's recording has a random id, so ``DIR/rrd/index.csv`` says which id is which cell;
the viewer's recording list then reads like results.csv.
"""

from __future__ import annotations

import csv
import subprocess
import sys
import warnings
from pathlib import Path

from arpz.experiment.results import read_rows


class MergeError(RuntimeError):
    pass


def recording_ids(path: Path) -> list[str]:
    from rerun.chunk import RrdReader

    with warnings.catch_warnings():
        # a CEDDP killed hard leaves no footer; the file still reads by scanning it
        warnings.simplefilter("ignore")
        return [e.recording_id for e in RrdReader(str(path)).recordings()]


def merge_recordings(directory: Path, *, timeout_s: float = 600.0) -> Path:
    """Write DIR/all_runs.rrd and DIR/rrd/index.csv from the rrd of every ok row."""
    rows = [r for r in read_rows(directory / "results.csv") if r["status"] == "ok" and r["rrd"]]
    files = [directory / r["rrd"] for r in rows if (directory / r["rrd"]).exists()]
    if not files:
        raise MergeError(f"{directory}: no recordings to merge")
    index = directory / "rrd" / "index.csv"
    with index.open("w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(["rrd", "recording_id", "rmax_hz", "depth", "config", "network", "repeat"])
        for row in rows:
            path = directory / row["rrd"]
            if path.exists():
                for rec in recording_ids(path):
                    cell = [row[k] for k in ("rmax_hz", "depth", "config", "network", "repeat")]
                    writer.writerow([row["rrd"], rec, *cell])
    merged = directory / "all_runs.rrd"
    result = subprocess.run(
        [sys.executable, "-m", "rerun", "rrd", "merge", *map(str, files), "-o", str(merged)],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        check=False,
    )
    if result.returncode != 0 or not merged.exists():
        raise MergeError(f"rerun rrd merge failed: {result.stderr[-500:]}")
    return merged
