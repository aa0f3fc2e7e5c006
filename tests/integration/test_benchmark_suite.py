"""``python -m benchmarks`` as a contributor runs it, on its cheapest entry (the optimisers'
solve times, in process): one table with the ratio, RESULTS.md's figure and a verdict, the
progress lines, the JSON, and an exit code that agrees with the table."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]


def test_the_suite_runs_one_quick_entry_and_its_exit_code_follows_the_table(
    tmp_path: Path,
) -> None:
    out = tmp_path / "suite.json"
    done = subprocess.run(
        [sys.executable, "-m", "benchmarks", "--quick", "--only", "optimiser", "--json", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    lines = done.stdout.splitlines()
    assert lines[:2] == [
        "| entry | ratio | measured | RESULTS.md | better | change | verdict |",
        "|---|---|---:|---:|---|---:|---|",
    ], done.stdout + done.stderr
    (row,) = [line for line in lines if line.startswith("| optimiser |")]
    cells = [cell.strip() for cell in row.strip("|").split("|")]
    assert cells[1] == "CVXPY / closed form, solve time" and cells[4] == "higher", row
    assert cells[2].endswith("x") and cells[3].endswith("x"), row  # measured, RESULTS.md's
    # a regression on a loaded host is measured again and fails only if both regressed: the
    # verdict may be either, the exit code must say the same
    failed = cells[6].startswith("FAIL")
    assert done.returncode == (1 if failed else 0), done.stdout + done.stderr
    assert lines[-1].startswith("suite: 1 entry in ") and lines[-1].endswith(
        "FAILED" if failed else "passed"
    )
    assert "optimiser (1/1): started" in done.stderr and "optimiser (1/1): done in" in done.stderr
    doc = json.loads(out.read_text())
    assert doc["quick"] is True and doc["passed"] is not failed
    (ratio,) = doc["ratios"]
    assert ratio["ratio"] == "CVXPY / closed form, solve time" and ratio["reference"] > 1
    assert ratio["measured"][0] > 1
