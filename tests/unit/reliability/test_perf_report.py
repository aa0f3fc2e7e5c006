"""The perf tool's pure reduction from recorded samples to the report."""

from __future__ import annotations

from arpz.perf.report import HEADER, Recorder, build_report, make_payload, percentile


def test_percentile_is_nearest_rank() -> None:
    values = [float(v) for v in range(1, 101)]
    assert (percentile(values, 50), percentile(values, 99), percentile(values, 100)) == (
        50,
        99,
        100,
    )
    assert percentile([], 50) == 0.0


def test_report_counts_duplicates_reordering_stalls_and_lateness() -> None:
    rec = Recorder()
    # seq, latency us, arrival s: 3 arrives before 2, 4 twice, a 0.5 s stall, 6 never comes
    for seq, lat_us, t in [
        (1, 100, 0.0),
        (3, 200, 0.001),
        (2, 9000, 0.002),
        (4, 60000, 0.003),
        (4, 100, 0.004),
        (5, 100, 0.504),
    ]:
        rec.add(seq, lat_us * 1000, t)
    report = build_report(
        rec,
        transport="arpz",
        key="k",
        size=24,
        rate_hz=100.0,
        sent=6,
        lost=0,
        retransmissions=1,
        nacks=1,
        duration_s=1.0,
    )
    assert (report.sent, report.received, report.unaccounted) == (6, 5, 1)
    assert (report.duplicates, report.out_of_order) == (1, 1)
    assert abs(report.longest_stall_ms - 500) < 1e-6
    # period 10 ms: late > 2 ms, too late > 10 ms
    assert (report.late, report.too_late) == (2, 1)
    assert report.latency_us is not None and report.latency_us.max == 60000


def test_payload_carries_seq_and_stamp_and_has_the_asked_size() -> None:
    payload = make_payload(7, 123, 1024)
    assert len(payload) == 1024 and HEADER.unpack_from(payload) == (7, 123)
    assert len(make_payload(1, 1, 4)) == HEADER.size


def test_a_payload_that_is_not_a_perf_sample_is_counted_apart() -> None:
    rec = Recorder()
    now = 1_700_000_000 * 10**9
    assert rec.add_payload(make_payload(7, now - 2_000, 24), now, 1.0)
    assert not rec.add_payload(b"\xff" * 40, now, 1.1)  # a seq beyond int64
    assert not rec.add_payload(b"short", now, 1.2)
    assert not rec.add_payload(make_payload(0, now, 24), now, 1.3)  # perf seqs start at 1
    assert not rec.add_payload(make_payload(8, 5, 24), now, 1.4)  # stamped in 1970
    report = build_report(
        rec, transport="arpz", key="k", size=24, rate_hz=0, sent=None, lost=0,
        retransmissions=0, nacks=0, duration_s=1.0,
    )  # fmt: skip
    assert (report.received, report.foreign, report.sent) == (1, 4, 7)
    assert report.latency_us is not None and report.latency_us.min == 2.0
