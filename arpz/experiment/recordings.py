"""One ``.rrd`` with every run: the CEDDP of each cell writes its own recording, and
``rerun rrd merge`` puts them side by side in ``DIR/all_runs.rrd`` (one recording per cell),
through arpz.ceddp.dashboard, the one module that knows Rerun.

Each cell's recording has a random id, so ``DIR/rrd/index.csv`` says which id is which cell;
the viewer's recording list then reads like results.csv.
"""

from __future__ import annotations

import csv
from pathlib import Path

from arpz.ceddp.dashboard import merge_rrd, rrd_recording_ids
from arpz.core.errors import ArpzError
from arpz.experiment.results import read_rows


class MergeError(ArpzError, RuntimeError):
    pass


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
                for rec in rrd_recording_ids(path):
                    cell = [row[k] for k in ("rmax_hz", "depth", "config", "network", "repeat")]
                    writer.writerow([row["rrd"], rec, *cell])
    merged = directory / "all_runs.rrd"
    failure = merge_rrd(files, merged, timeout_s=timeout_s)
    if failure is not None:
        raise MergeError(failure)
    return merged
