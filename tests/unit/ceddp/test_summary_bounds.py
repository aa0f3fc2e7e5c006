"""The summary never reports more lost than the robot sent and the CEDDP did not receive."""

from __future__ import annotations

from arpz.ceddp.cache_control import CacheControl
from arpz.ceddp.ingest import Ingest
from arpz.ceddp.planner import Planner
from arpz.ceddp.summary import topic_summary
from arpz.messages import RobotStats, Sample, TopicCounters, encode, writer_id

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
