"""The ``quick`` preset end to end: real CEDDP and robot processes behind real netem proxies,
results.csv complete and consistent, the expected loss pattern, the report, and a resumed run
that has nothing left to do."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from arpz.experiment.presets import quick
from arpz.experiment.report import consistency
from arpz.experiment.results import read_rows

# The mission's robots need data under 0.3 s old for 90 s; run beside the experiment's fleet
# on two shared cores it starved (p99 0.7-1.6 s, the mission timed out, old code and new
# alike), and the experiment lost samples on a clean link beside other tests, unit tests too:
# it runs with the whole machine to itself (tests/conftest.py, cpu_share).
pytestmark = [
    pytest.mark.integration,
    pytest.mark.slow,
    pytest.mark.cpu_exclusive(whole_machine=True),
]


def run(*args: str, timeout_s: float) -> tuple[int, str]:
    """``python -m arpz.experiment ...`` in its own session, so a timeout ends every process it
    started (CEDDP, robots), not only the runner."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "arpz.experiment", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    try:
        out, _ = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, _ = proc.communicate()
        pytest.fail(f"the experiment did not finish within {timeout_s:.0f} s:\n{out[-3000:]}")
    return proc.returncode, out


@pytest.mark.timeout(300)
def test_quick_preset(tmp_path: Path) -> None:
    out = tmp_path / "quick"
    started = time.monotonic()
    code, text = run("run", "quick", "--out", str(out), timeout_s=240)
    elapsed = time.monotonic() - started
    assert code == 0, text[-3000:]
    assert elapsed < 180, f"quick took {elapsed:.0f} s"
    assert "ETA" in text

    rows = read_rows(out / "results.csv")
    spec = quick()
    assert {
        tuple(r[k] for k in ("rmax_hz", "depth", "config", "repeat", "network", "middleware"))
        for r in rows
    } == {c.key for c in spec.cells()}
    assert all(r["status"] == "ok" for r in rows), [r["error"] for r in rows]
    assert consistency(rows) == [], rows
    for row in rows:
        assert int(row["samples_sent"]) > 0 and int(row["hello_sent"]) > 0
        assert int(row["final_reports"]) == 3, row  # the shutdown runs over clean links
        assert (out / row["rrd"]).stat().st_size > 0
        # the CEDDP's staleness and the reliable downlink made it into the row
        p50, p99, top = (float(row[f"staleness_ms_{q}"]) for q in ("p50", "p99", "max"))
        # on the CEDDP's clock, each robot's estimated offset taken out: on one host the true
        # offset is 0, so the estimate is its own error, and a value read just before it was
        # sent can come out below 0 by about that much (p50 -0.65 ms beside a spinner, stop 33;
        # the row has the final estimates, the run used earlier ones too: 1 ms more)
        offset_error = float(row["clock_offset_ms_max"] or 0) + 1.0
        assert -offset_error < p50 <= top and p99 <= top, row
        assert int(row["hello_hops_written"]) > 0, row  # the relay's and the origin's hops
        assert row["downlink_reconciled"] == "yes", row["downlink_unreconciled"]
        assert int(row["incompatible_qos"]) == 0 and int(row["samples_refused"]) == 0, row
    by = {(r["network"], r["depth"], r["config"]): r for r in rows}

    # A deep history on a clean link: at 3 robots x 6 topics x 1 kHz this 2-core host is past
    # its capacity (10 000-50 000 resends with no link loss). With the whole machine to itself
    # the cell lost 0-639 samples (resends later than the reader's reorder timeout, declared
    # lost and counted) and 0-20 of about 60 Hellos (a round trip over 2 s; the Hello p99 was
    # 0.8-1.9 s). Zero loss is a figure of the experiment on a host that keeps up
    # (EXPERIMENTS.md), not of a test on a shared 2-core VM; here, the paper's point: depth
    # saves nearly everything that depth 1 loses, samples and Hellos alike.
    clean = by[("lan", "1000", "baseline")]
    shallow = by[("lan", "1", "baseline")]

    def lost_share(row: dict[str, str], what: str, of: str) -> float:
        return int(row[what]) / max(1, int(row[of]))

    # Where depth 1 loses, the deep history must lose at most a fifth (samples) or a half
    # (Hellos) of its share. In a fast window depth 1 loses nothing on the clean link either
    # (samples: CI of 7882689, 0 and 0; Hellos: CI of 667cc48), and there is then nothing for
    # depth to save; the deep history still loses the resends its reader gave up on when the
    # host is past capacity, counted: 4.1 % of its samples, with depth 1's 0, beside a busy
    # loop (stop 40). Then a bound on its own share.
    for what, of, ratio, alone in (
        ("samples_lost", "samples_sent", 5, 0.1),
        ("hello_lost", "hello_sent", 2, 0.5),
    ):
        deep_share, shallow_share = lost_share(clean, what, of), lost_share(shallow, what, of)
        if shallow_share > 0:
            assert deep_share * ratio <= shallow_share, (what, clean, shallow)
        else:
            assert deep_share < alone, (what, clean, shallow)
    assert float(clean["link_loss_pct"]) == 0

    lossy = by[("wifi-bad", "1", "baseline")]
    assert float(lossy["link_loss_pct"]) > 2, lossy
    assert float(lossy["sample_loss_pct"]) > 1, lossy
    assert int(lossy["samples_overwritten_unacked"]) > 0, lossy
    deep = by[("wifi-bad", "1000", "baseline")]
    assert float(deep["sample_loss_pct"]) < float(lossy["sample_loss_pct"]), (deep, lossy)

    for network in ("lan", "wifi-bad"):
        opt = by[(network, "opt", "lc+opt")]
        # the optimiser's R and D were assigned and applied by all three robots
        assert float(opt["rate_hz"]) < 1000 and int(opt["qos_depth"]) > 1, opt
        assert int(opt["qos_applied"]) == 3, opt
        assert int(opt["samples_held_back"]) > 0, opt  # the local cache held repeats back

    report = (out / "REPORT.md").read_text(encoding="utf-8")
    assert "Every ok row reconciles" in report
    for metric in ("latency", "loss", "sample_loss", "staleness"):
        assert (out / "figures" / f"experiment_{metric}_lan.png").stat().st_size > 1000

    # one recording per cell, side by side in all_runs.rrd, indexed by cell
    assert (out / "all_runs.rrd").stat().st_size > 0
    index = (out / "rrd" / "index.csv").read_text(encoding="utf-8").splitlines()
    assert len(index) == 1 + len(rows)

    before = (out / "results.csv").read_bytes()
    code, text = run("run", "quick", "--out", str(out), timeout_s=60)
    assert code == 0, text
    assert f"{len(rows)} already done, 0 to run" in text
    assert (out / "results.csv").read_bytes() == before
