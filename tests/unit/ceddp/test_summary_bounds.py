"""The summary never reports more lost than the robot sent and the CEDDP did not receive, and
computes its percentiles after the ingest lock is released."""

from __future__ import annotations

import pytest

from arpz.ceddp.cache_control import CacheControl
from arpz.ceddp.control import RobotRecord
from arpz.ceddp.ingest import Ingest
from arpz.ceddp.planner import Planner
from arpz.ceddp.summary import Deferred, resolve, robot_summary, topic_summary
from arpz.core.messages import RobotStats, Sample, TopicCounters, encode, writer_id
from arpz.core.percentiles import RELATIVE_ERROR

KEY = "arpz/f/robot/r1/sensor/pir"


def test_loss_claimed_by_seqs_never_sent_is_implausible_not_lost() -> None:
    ingest = Ingest("f", Planner(), CacheControl(enabled=False))
    writer = writer_id("r1", "inc1")
    # seqs 1..5 arrive, then one at 9 000 after 10 s of silence: plausible as an outage
    for seq, at_s in ((1, 1.0), (2, 1.01), (3, 1.02), (4, 1.03), (5, 1.04), (9_000, 11.04)):
        sample = Sample(writer, seq, 1000, "detect")  # type: ignore[arg-type]
        ingest.handle_sensor(KEY, encode(sample), int(at_s * 1e9))
    m = ingest.topics[("r1", "pir")]
    assert m.lost == 8_994
    # ... but the robot's final counters say it sent 10 samples, the last with seq 10
    stats = RobotStats(
        "r1", "inc1", 0, True, {"pir": TopicCounters(produced=10, sent=10, last_seq=10)}
    )
    row = topic_summary(ingest, m, stats)
    assert row["received"] == 6 and row["lost"] == 4
    assert row["implausible_lost"] == 8_990
    assert row["lost"] + row["received"] == row["sent"]


def test_deferred_percentiles_equal_the_ones_computed_under_the_lock() -> None:
    """The server builds each robot's row under the ingest lock with its percentiles deferred
    and computes them after releasing it: the figures must be the same."""
    ingest = Ingest("f", Planner(), CacheControl(enabled=False))
    writer = writer_id("r1", "inc1")
    for seq in range(1, 400):
        sample = Sample(writer, seq, seq * 1_000_000, seq % 7)  # type: ignore[arg-type]
        ingest.handle_sensor(KEY, encode(sample), seq * 1_000_000 + (seq % 13) * 100_000)
    report = RobotRecord().as_report()
    row = robot_summary(ingest, "r1", report, defer=True)
    assert isinstance(row["latency_ms_p99"], Deferred)
    assert isinstance(row["topics"]["pir"]["staleness_ms_p50"], Deferred)
    assert resolve(row) == robot_summary(ingest, "r1", report)
    assert resolve(row)["latency_ms_p99"] == pytest.approx(1.2, abs=0.05)


def test_a_robot_s_latency_pools_its_topics_and_is_the_same_deferred() -> None:
    """The robot's p50 and p99 are of every sensor topic's samples together (hello aside),
    pooled after the ingest lock is released when deferred."""
    ingest = Ingest("f", Planner(), CacheControl(enabled=False))
    writer = writer_id("r1", "inc1")
    latencies_ms = {"pir": 1.0, "light": 9.0}  # every sample of a topic: the same latency
    for topic, latency_ms in latencies_ms.items():
        key = f"arpz/f/robot/r1/sensor/{topic}"
        for seq in range(1, 101):
            sample = Sample(writer, seq, seq * 1_000_000, seq)  # type: ignore[arg-type]
            ingest.handle_sensor(key, encode(sample), seq * 1_000_000 + int(latency_ms * 1e6))
    report = RobotRecord().as_report()
    deferred = resolve(robot_summary(ingest, "r1", report, defer=True))
    assert deferred == robot_summary(ingest, "r1", report)
    assert deferred["latency_ms_p99"] == pytest.approx(9.0)  # the slower topic's
    # between the two halves: halfway between 1.0 and 9.0, each read from its bucket
    assert deferred["latency_ms_p50"] == pytest.approx(5.0, rel=RELATIVE_ERROR)
    assert deferred["topics"]["pir"]["latency_ms_p99"] == pytest.approx(1.0)


def test_under_the_lock_a_robot_s_row_only_drains_its_windows() -> None:
    """Folding the windows into the histograms and copying them waits for ``resolve``, after
    the ingest lock is released; the row's maxima already count the window's values."""
    ingest = Ingest("f", Planner(), CacheControl(enabled=False))
    writer = writer_id("r1", "inc1")
    for seq in range(1, 51):
        sample = Sample(writer, seq, seq * 1_000_000, seq)  # type: ignore[arg-type]
        ingest.handle_sensor(KEY, encode(sample), seq * 1_000_000 + seq * 10_000)
    m = ingest.topics[("r1", "pir")]
    assert m.latency_ms.count == 0 and m.latency_ms.total == 50  # all in the window
    stale = m.staleness_ms.total
    row = robot_summary(ingest, "r1", RobotRecord().as_report(), defer=True)
    assert m.latency_ms.count == 0 and m.latency_ms.total == 0  # drained, not folded
    assert row["latency_ms_max"] == pytest.approx(0.5)  # seq 50: 500 us late
    resolved = resolve(row)
    assert m.latency_ms.count == 50 and m.staleness_ms.count == stale > 0  # folded at resolve
    assert resolved["topics"]["pir"]["latency_ms_p50"] == pytest.approx(0.255, rel=RELATIVE_ERROR)
