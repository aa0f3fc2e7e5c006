"""Bad input from a raw Zenoh client against a running CEDDP process (no access control).

A buggy robot or a stranger on an open network can put anything on any key. The CEDDP must count
each bad thing where the summary shows it, keep ingesting the real robots' samples without loss,
never crash, and keep its memory bounded. The raw client uses blocking publishers for the floods
so that Zenoh drops nothing on the way and every count can be checked exactly.
"""

from __future__ import annotations

import itertools
import json
import os
import statistics
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgspec
import pytest

from arpz.ceddp.ingest import MAX_WRITERS_PER_TOPIC
from arpz.core.messages import CEDDP_STATS_DECODER, Hello, Sample, encode
from arpz.core.protocol import wire
from arpz.transport.zenoh import ZenohTransport
from tests.integration.fleet import STEADY_MALLOC, ceddp, robots, settle, write_robot
from tests.integration.secure_fleet import rss_mb
from tests.support import client, wait_until

# floods at full speed: the other worker's timing-bound tests must not run beside them, and
# their own bounds need the machine (a unit test beside the memory rounds: the late peaks rose
# 75 MB where 40 are allowed, in-flight payloads of a slower CEDDP) (tests/conftest.py)
pytestmark = [pytest.mark.integration, pytest.mark.cpu_exclusive(whole_machine=True)]
R1 = "arpz/itest/robot/robot1"
#: the tests of raw bytes run both sides in plain mode, where raw puts are the robots' own kind
#: of traffic; in channel mode a plain put is refused whole (tests/integration/test_downlink.py)
PLAIN = 'reliability = "none"\n'

#: not msgpack, or msgpack of the wrong shape or type, each a decode error on a sensor key
MALFORMED = [
    b"",
    b"\xc1",
    b"not msgpack at all",
    b"\x94\xa3\xff\xfe\xfd\x01\x02\xc3",  # a writer that is not UTF-8
    b"\xdd\xff\xff\xff\xff",  # an array header claiming 4 billion elements
    b"\x91" * 10_000 + b"\xc0",  # 10 000 nested arrays
    msgspec.msgpack.encode({"writer": "x", "seq": 1, "stamp_ns": 1, "value": 1.0}),
    msgspec.msgpack.encode(["robot1:x", "one", 1, 1.0]),  # seq of the wrong type
    msgspec.msgpack.encode(["robot1:x", 1, 1.5, 1.0]),  # stamp of the wrong type
    msgspec.msgpack.encode(["robot1:x", 1, 1, None]),  # value of no sensor type
    msgspec.msgpack.encode(["robot1:x", 1, 1, [1.0, 2.0]]),
    msgspec.msgpack.encode(["robot1:x", 1, 1, {"a": 1}]),
    msgspec.msgpack.encode(["robot1:x", 1, 1]),  # too short
]
OVERSIZED = [
    os.urandom(10_000_000),  # 10 MB of noise
    msgspec.msgpack.encode(["robot1:x", 1, 1, os.urandom(10_000_000)]),  # 10 MB bin value
]
FLOOD = 10_000
#: the abuse is repeated: memory the first rounds take may stay (allocator pools, Zenoh buffers)
#: and readings move by tens of MB (10 MB payloads in flight), but it must level off: over 20
#: rounds it grows for the first few, then stays flat (``-s`` prints the readings). Twenty
#: rounds also take the forged writers past the per-topic writer limit.
ROUNDS = 20
#: the CEDDP writes its summary this often while running, for the tests that poll it
SUMMARY_EVERY = "summary_period_s = 0.2\n"


def _robot1(tmp: Path) -> dict[str, Any]:
    """robot1's row in the CEDDP's latest summary (written atomically); empty before one."""
    try:
        summary = json.loads((tmp / "summary.json").read_text())
    except FileNotFoundError:
        return {}
    row: dict[str, Any] = summary["robots"].get("robot1", {})
    return row


class Rates:
    """The CEDDP's own per-topic arrival rates (CeddpStats), as any client can read them."""

    def __init__(self) -> None:
        self.reports: list[dict[tuple[str, str], float]] = []
        self._lock = threading.Lock()

    def __call__(self, _key: str, payload: bytes, _att: bytes | None) -> None:
        stats = CEDDP_STATS_DECODER.decode(payload)
        with self._lock:
            self.reports.append({(t.robot, t.topic): t.rate_hz for t in stats.topics})

    def count(self) -> int:
        with self._lock:
            return len(self.reports)

    def quiet_from(self, index: int, topic: tuple[str, str]) -> Callable[[], bool]:
        """A predicate: some report from ``index`` on saw nothing arrive on ``topic``."""
        return lambda: any(r.get(topic, 0) == 0 for r in self.since(index))

    def since(self, index: int) -> list[dict[tuple[str, str], float]]:
        with self._lock:
            return self.reports[index:]


def _abuse(raw: ZenohTransport, round_no: int) -> None:
    """One round of everything bad, each on the key where the CEDDP must count it."""
    garbage = raw.publisher(f"{R1}/sensor/pir", block=True)
    for payload in MALFORMED:
        garbage.put(payload)
    big = raw.publisher(f"{R1}/sensor/imu", block=True)
    for payload in OVERSIZED:
        big.put(payload)
    hello = raw.publisher(f"{R1}/sensor/hello", block=True)
    hello.put(encode(Sample("robot1:x", 1, 1, 1.0)))  # a Sample where a Hello goes
    hello.put(msgspec.msgpack.encode(["robot1:x", 1, 1, "robot1", 1, 1]))  # too short
    for _ in range(3):
        raw.put(f"{R1}/bogus", b"\x00")  # a key outside docs/protocol.md
    raw.put("arpz/otherfleet/robot/robot1/sensor/pir", b"\xc1")  # another fleet
    # floods: garbage on a real topic, and a forged writer on a topic of its own
    for _ in range(FLOOD):
        garbage.put(b"\xc1 flood")
    forged = raw.publisher(f"{R1}/sensor/flood", block=True)
    for seq in range(1, FLOOD + 1):
        forged.put(encode(Sample(f"intruder:{round_no:012d}", seq, 1, float(seq % 7))))


def test_bad_input_is_counted_and_the_fleet_keeps_flowing(tmp_path: Path) -> None:
    with ceddp(tmp_path, extra=PLAIN, env=STEADY_MALLOC) as (server, endpoint):
        pid = server.popen.pid
        rates = Rates()
        config = write_robot(
            tmp_path, "robot1", endpoint, preset="machine2", rate_hz=100, top=PLAIN
        )
        with robots(tmp_path, [config]) as procs, client(endpoint) as raw:
            raw.subscribe("arpz/itest/ceddp/stats", rates)
            wait_until(lambda: "robot robot1 joined" in server.output(), what="robot1 joined")
            settle(1.5)  # deliberately: warm-up (imports, first dashboard frames, allocator pools)

            rss = [rss_mb(pid)]
            for round_no in range(ROUNDS):
                _abuse(raw, round_no)
                wait_until(
                    rates.quiet_from(rates.count() + 1, ("robot1", "flood")),
                    timeout_s=20,
                    what="the CEDDP to finish a round of floods",
                )
                rss.append(rss_mb(pid))
            # the robot's own topics keep arriving after all that
            mark = rates.count()
            wait_until(
                lambda: any(r.get(("robot1", "ultrasonic"), 0) > 0 for r in rates.since(mark + 1)),
                timeout_s=15,
                what="robot1's samples still arriving after the floods",
            )
            settle(1.0)  # deliberately: a second of plain traffic before the last memory reading
            rss.append(rss_mb(pid))
            assert procs[0].interrupt() == 0, procs[0].output()
        assert server.interrupt() == 0, server.output()

    summary = json.loads((tmp_path / "summary.json").read_text())
    topics = summary["robots"]["robot1"]["topics"]
    assert topics["pir"]["decode_errors"] == ROUNDS * (len(MALFORMED) + FLOOD)
    # refused undecoded: larger than max_sample_bytes (64 KiB for kinds not announced otherwise)
    assert topics["imu"]["oversize"] == ROUNDS * len(OVERSIZED)
    assert topics["imu"]["decode_errors"] == 0
    assert topics["hello"]["decode_errors"] == ROUNDS * 2
    # each round's forged writer is a writer of its own, not a loss, until the topic tracks
    # MAX_WRITERS_PER_TOPIC of them; the rest are refused and counted
    accepted = min(ROUNDS, MAX_WRITERS_PER_TOPIC)
    assert topics["flood"]["received"] == accepted * FLOOD and topics["flood"]["lost"] == 0
    assert topics["flood"]["writers_over_limit"] == (ROUNDS - accepted) * FLOOD
    assert summary["ingest"]["unknown_control_keys"] == ROUNDS * 3
    assert "otherfleet" not in json.dumps(summary["robots"])
    for topic, t in topics.items():
        if topic in ("hello", "flood", "imu"):  # imu: only the oversized payloads (not machine2)
            continue
        # the real samples: nothing lost, nothing undecodable among them
        assert t["produced"] == t["sent"] + t["held_back"] > 0, (topic, t)
        assert t["received"] == t["sent"] and t["lost"] == 0, (topic, t)
    # each round pushes 20 MB of oversized payloads and 20 000 flood messages through the CEDDP.
    # RSS moves without a leak: one reading may jump by tens of MB and come back (payloads in
    # flight), and the level may step up by 30-40 MB at a random round and stay (allocator
    # caches, even with STEADY_MALLOC). A leak is a rise every round. So the second half of the
    # rounds counts as grown only when both its peak and its level (median) are 40 MB above the
    # first half's: a leak of 5 MB a round raises both by about 50, while each pattern seen
    # without one raised only one of them (a clean-clone CI run: one reading 40 MB up and back,
    # peak +40, level +12; a local run: two steps, level +84, peak +21), and rises by 2 MB or
    # more in over a third of the second half's rounds, where steps rose in at most three (two
    # runs of stop 30 failed on peak and level alone: a step of 43 MB with +4 and +3 around it,
    # peak +50, level +49; steps of 7, 37 and 16 MB, peak +52, level +67; a leak of 5 MB a round
    # rises in all 11, and one that shows as 10 MB every other round in 5). No reading may be
    # more than 200 MB above the start (keeping each round's payloads would add 400).
    report = f"RSS (MB) before, after each round, at the end: {rss}"
    print(report)
    half = 1 + ROUNDS // 2
    peak_rise = max(rss[half:]) - max(rss[1:half])
    level_rise = statistics.median(rss[half:]) - statistics.median(rss[1:half])
    late = rss[half - 1 :]
    rising = sum(after - before >= 2.0 for before, after in itertools.pairwise(late))
    assert peak_rise < 40 or level_rise < 40 or rising <= (len(late) - 1) // 3, report
    assert max(rss) - rss[0] < 200, report


def test_undecodable_reports_are_in_the_summary(tmp_path: Path) -> None:
    with (
        ceddp(tmp_path, extra=PLAIN + SUMMARY_EVERY) as (server, endpoint),
        client(endpoint) as raw,
    ):
        for kind in ("stats", "announce", "telemetry"):
            raw.put(f"{R1}/{kind}", b"\xc1 not a report")
        raw.put(f"{R1}/sensor/pir", encode(Sample("robot1:x", 1, 1, "detect")))  # a marker
        wait_until(
            lambda: (
                _robot1(tmp_path).get("topics", {}).get("pir", {}).get("received") == 1
                and _robot1(tmp_path).get("control_decode_errors") == 3
            ),
            what="the marker and the three undecodable reports handled",
        )
        assert server.interrupt() == 0, server.output()
    summary = json.loads((tmp_path / "summary.json").read_text())
    robot1 = summary["robots"]["robot1"]
    assert robot1["topics"]["pir"]["received"] == 1
    assert robot1.get("control_decode_errors") == 3, sorted(robot1)


def test_invented_topic_names_cannot_grow_the_ceddp_without_bound(tmp_path: Path) -> None:
    with (
        ceddp(tmp_path, extra=PLAIN, env=STEADY_MALLOC) as (server, endpoint),
        client(endpoint) as raw,
    ):
        pid = server.popen.pid
        settle(1.0)  # deliberately: the CEDDP idles a second after start-up before memory is read
        rss_before = rss_mb(pid)
        payload = encode(Sample("robot1:000000000000", 1, 1, 1.0))
        # all under one robot id: what a robot may do even with access control on
        for i in range(20_000):
            raw.put(f"{R1}/sensor/t{i}", payload)
        # deliberately 3 s to ingest the burst before memory is read: raw puts may be dropped
        # on the way, so there is no count to wait for
        settle(3.0)
        growth = rss_mb(pid) - rss_before
        assert server.interrupt() == 0, server.output()  # and it still stops in time
    assert growth < 40, f"the CEDDP grew by {growth:.0f} MB"
    summary = json.loads((tmp_path / "summary.json").read_text())
    tracked = summary["robots"]["robot1"]["topics"]
    assert 0 < len(tracked) <= 64, len(tracked)  # max_topics_per_robot's default
    # (raw puts may be dropped on the way under load, so the sum is at most what was sent)
    assert 0 < summary["ingest"]["over_limit"] <= 20_000 - len(tracked)


def test_a_forged_hello_cannot_stop_the_ceddp(tmp_path: Path) -> None:
    """A Hello whose origin is not a robot name is counted and dropped by the relay (see
    in test_fuzz_decoders.py), but the worker survives it and keeps ingesting."""
    with (
        ceddp(tmp_path, relay="robot2", extra=PLAIN + SUMMARY_EVERY) as (server, endpoint),
        client(endpoint) as raw,
    ):
        for origin in ("*", "Robot/1", ""):
            raw.put(f"{R1}/sensor/hello", encode(Hello("robot1:x", 1, 1, origin, 1, 1, 2)))
        pir = raw.publisher(f"{R1}/sensor/pir", block=True)
        for seq in range(1, 101):
            pir.put(encode(Sample("robot1:000000000000", seq, 1, "detect")))
        wait_until(
            lambda: _robot1(tmp_path).get("topics", {}).get("pir", {}).get("received") == 100,
            what="the 100 samples after the forged Hellos ingested",
        )
        assert server.popen.poll() is None, server.output()
        assert server.interrupt() == 0, server.output()
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["robots"]["robot1"]["topics"]["pir"]["received"] == 100


CHANNEL = '[sensor_qos]\nreliability = "reliable"\nhistory = "keep_last"\ndepth = 50\n'


def test_forged_heartbeats_cannot_blackhole_a_reliable_topic(tmp_path: Path) -> None:
    with ceddp(tmp_path, extra=CHANNEL) as (server, endpoint):
        config = write_robot(tmp_path, "robot1", endpoint, preset="machine2")
        config.write_text(config.read_text() + CHANNEL)
        tokens: list[str] = []
        with robots(tmp_path, [config]) as procs, client(endpoint) as raw:
            # the writers announce themselves with liveliness tokens anyone may watch
            raw.watch_liveliness(f"{R1}/sensor/*/rel/w/*/*", lambda key, alive: tokens.append(key))
            wait_until(lambda: len(tokens) >= 5, what="robot1's writer tokens")
            real = list(tokens)
            for key in real:
                split = wire.split_control_key(key, "w", 2)
                assert split is not None, key
                topic, (writer_hex, _qos) = split
                guid = bytes.fromhex(writer_hex)
                for i in range(100):  # "I have written up to 10**12": numbers never sent
                    raw.put(
                        wire.heartbeat_key(topic, writer_hex),
                        wire.encode_heartbeat(0, guid, 1, 10**12 + i, i + 1),
                    )
                # and one sample far ahead: seq 10**6 (issue 15: it made the reader count a
                # million lost and drop the real stream after it)
                raw.put(topic, b"\xc1", attachment=wire.encode_data(0, guid, 10**6, 1))
            # samples from invented writers: at most 16 per key are matched, the rest refused
            for i in range(200):
                raw.declare_token(wire.writer_token(f"{R1}/sensor/pir", f"{i:016x}", "RVA_0_0"))
            settle(2.0)  # deliberately: 2 s of the robot's stream alongside the forged input
            assert procs[0].interrupt() == 0, procs[0].output()
        assert server.interrupt() == 0, server.output()
    summary = json.loads((tmp_path / "summary.json").read_text())
    for topic, t in summary["robots"]["robot1"]["topics"].items():
        assert t["received"] == t["sent"] and t["lost"] == 0, (topic, t)
    channel = summary["ingest"]["channel"]
    # refused as implausible (beyond what a writer can have written since it was last heard),
    # never counted lost: the heartbeats and the far-ahead samples, one per writer token seen
    assert summary["ingest"]["channel_lost"] == 0 and channel["lost"] == 0, channel
    assert channel["implausible"] >= len(real) * 101, channel
    assert channel["writers_refused"] > 0, channel


def test_forged_acknacks_cost_bounded_work_and_lose_nothing(tmp_path: Path) -> None:
    """ACKNACKs in the name of the CEDDP's real reader (its GUID is in its liveliness token)
    asking for every number up to 2**63 and acknowledging numbers never sent, and ACKNACKs from
    readers that do not exist: the robot's writers resend at most their budget per message, the
    reader drops the duplicates, and every real sample arrives exactly once."""
    with ceddp(tmp_path, extra=CHANNEL) as (server, endpoint):
        config = write_robot(tmp_path, "robot1", endpoint, preset="machine2")
        config.write_text(config.read_text() + CHANNEL)
        writers: list[str] = []
        readers: list[str] = []
        with robots(tmp_path, [config]) as procs, client(endpoint) as raw:
            raw.watch_liveliness(f"{R1}/sensor/*/rel/w/*/*", lambda key, _a: writers.append(key))
            raw.watch_liveliness(f"{R1}/sensor/*/rel/r/*/*", lambda key, _a: readers.append(key))
            wait_until(lambda: len(writers) >= 5 and len(readers) >= 5, what="channel tokens")
            reader_of = {}
            for key in list(readers):
                split = wire.split_control_key(key, "r", 2)
                assert split is not None, key
                reader_of[split[0]] = split[1][0]
            for key in list(writers):
                split = wire.split_control_key(key, "w", 2)
                assert split is not None, key
                topic, (writer_hex, _qos) = split
                writer = bytes.fromhex(writer_hex)
                for reader_hex in (reader_of[topic], "00000000deadbeef"):
                    reader = bytes.fromhex(reader_hex)
                    everything = wire.encode_acknack(reader, writer, 1, 1, [(1, wire.MAX_SEQ)])
                    beyond = wire.encode_acknack(reader, writer, 10**12, 2, [])
                    for payload in (everything, beyond) * 20:
                        raw.put(wire.acknack_key(topic, writer_hex, reader_hex), payload)
            settle(2.0)  # deliberately: 2 s of the robot's stream after the forged ACKNACKs
            assert procs[0].popen.poll() is None, procs[0].output()
            assert procs[0].interrupt() == 0, procs[0].output()
        assert server.interrupt() == 0, server.output()
    summary = json.loads((tmp_path / "summary.json").read_text())
    robot1 = summary["robots"]["robot1"]
    for topic, t in robot1["topics"].items():
        assert t["produced"] == t["sent"] + t["held_back"] + t["write_failures"] > 0, (topic, t)
        assert t["received"] == t["sent"] and t["lost"] == 0, (topic, t)
    # the forged requests for resends were served, within the writers' budget per message
    assert 0 < robot1["retransmitted"] <= 5 * 20 * 256
    assert summary["ingest"]["channel"]["duplicates"] > 0


#: report floods from one robot's own keys (allowed by the access control): garbage, msgpack
#: nested deeper than msgspec follows, and 1 MB reports (over max_report_bytes)
REPORT_FLOOD = [b"\xc1 garbage", b"\x91" * 100_000 + b"\xc0", b"\x80" + os.urandom(1_000_000)]


def test_a_report_flood_from_one_robot_is_bounded_and_others_still_get_through(
    tmp_path: Path,
) -> None:
    """Issue 15, item 3: robot 9 floods its own stats, announce and telemetry keys for 5 s.
    The CEDDP's memory stays within 150 MB of where it started and stops growing with the flood, its
    log within 64 kB (one line per cause per 10 s), and a robot that joins during the flood is
    seen within 2 s (the control queue keeps the latest report per key, so a flood waits behind
    nothing and nothing waits behind it)."""
    with (
        ceddp(tmp_path, extra=PLAIN, env=STEADY_MALLOC) as (server, endpoint),
        client(endpoint) as raw,
    ):
        pid = server.popen.pid
        settle(1.5)  # deliberately: warm-up before the first memory reading
        rss = [rss_mb(pid)]
        log_before = len(server.output())
        robot9 = "arpz/itest/robot/robot9"
        publishers = [
            raw.publisher(f"{robot9}/{kind}", block=True)
            for kind in ("stats", "announce", "telemetry")
        ]
        stop = threading.Event()
        sent = [0]

        def flood() -> None:
            while not stop.is_set():
                for publisher in publishers:
                    for payload in REPORT_FLOOD:
                        publisher.put(payload)
                        sent[0] += 1

        flooder = threading.Thread(target=flood, daemon=True)
        flooder.start()
        try:
            settle(2.0)  # deliberately: 2 s into the flood before robot2 joins
            with client(endpoint) as other:
                joined_at = time.monotonic()
                other.declare_token("arpz/itest/robot/robot2/presence")
                wait_until(
                    lambda: "robot robot2 joined" in server.output(),
                    timeout_s=2.0,
                    what="robot2's presence handled during the flood",
                )
                join_delay_s = time.monotonic() - joined_at
                settle(3.0)  # deliberately: the flood goes on (5 s in all)
                rss.append(rss_mb(pid))
        finally:
            stop.set()
            flooder.join(timeout=10)
        settle(3.0)  # deliberately: 3 s after the flood, for memory to fall back to its plateau
        rss.append(rss_mb(pid))
        log_size = len(server.output()) - log_before
        assert server.interrupt() == 0, server.output()[-3000:]
    summary = json.loads((tmp_path / "summary.json").read_text())
    control = summary["ingest"]["control"]
    robot9_errors = summary["robots"]["robot9"]["control_decode_errors"]
    report = (
        f"{sent[0]} reports sent; RSS (MB) before, during, after: {rss}; log {log_size} B; "
        f"robot2 seen after {join_delay_s:.2f} s; control {control}; decode errors {robot9_errors}"
    )
    print(report)
    assert sent[0] > 1000, report
    assert control["reports_oversize"] > 0 and robot9_errors > 0, report
    # every report was refused as oversize, coalesced, or decoded (and failed): none vanished
    assert control["reports_oversize"] + control["coalesced"] + robot9_errors <= sent[0], report
    # bounded during the flood, and no growth once it stopped (a plateau). What the allocator
    # keeps of the peak depends on the load: alone +30-41 MB after (three runs), in CI beside
    # another test process +115 MB after with +120 MB during (173 -> 293 -> 288 MB); the old
    # "within 100 MB after" failed there while memory had plateaued
    assert max(rss) - rss[0] < 150 and rss[-1] <= rss[1] + 10, report
    assert log_size < 64_000, report
