"""Bundles through a real router: a robot's sensor messages of one tick cross the link as one
Zenoh message, the CEDDP reconciles every topic, and a plain subscriber of one topic still gets
that topic's samples (its subscription is widened to the siblings and filtered)."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import pytest
import zenoh

from arpz.channel import Reader, Writer
from arpz.channel.bundling import Bundler
from arpz.core.protocol import bundle, wire
from arpz.core.protocol.qos import QosProfile
from arpz.core.transport import SessionSettings
from arpz.transport.zenoh import ZenohTransport
from tests.integration.fleet import ceddp, robots, settle
from tests.support import HeldHeartbeats, client, router, wait_until

pytestmark = pytest.mark.integration


def _client(endpoint: str) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


def _run(tmp_path: Path, top: str) -> tuple[dict[str, int], list[str], dict[str, object]]:
    """(raw Zenoh messages by key's last chunk, one topic's keys through arpz's transport,
    the CEDDP's summary of the robot)."""
    raw: dict[str, int] = {}
    lock = threading.Lock()

    def count(sample: zenoh.Sample) -> None:
        with lock:
            last = str(sample.key_expr).rpartition("/")[2]
            raw[last] = raw.get(last, 0) + 1

    one_topic: list[str] = []
    with ceddp(tmp_path) as (server, endpoint):
        config = tmp_path / "robot1.toml"
        config.write_text(
            f'robot_id = "robot1"\nfleet = "itest"\nconnect = ["{endpoint}"]\n'
            f'preset = "machine1"\npreset_rate_hz = 50\nstats_period_s = 0.2\n{top}'
            "[local_cache]\nenabled = false\n"  # every reading is sent: six messages a tick
        )
        session = _client(endpoint)
        arpz_side = ZenohTransport.open(SessionSettings(connect=[endpoint]))
        try:
            session.declare_subscriber("arpz/itest/robot/robot1/sensor/*", count)
            arpz_side.subscribe(
                "arpz/itest/robot/robot1/sensor/imu", lambda k, _p, _a: one_topic.append(k)
            )
            with robots(tmp_path, [config]) as procs:
                wait_until(lambda: "robot robot1 joined" in server.output(), what="robot joined")
                settle(2.0)
                assert procs[0].interrupt(timeout_s=30) == 0, procs[0].output()
            assert server.interrupt(timeout_s=60) == 0, server.output()
        finally:
            arpz_side.close()
            session.close()
    summary = json.loads((tmp_path / "summary.json").read_text())
    return raw, one_topic, summary["robots"]["robot1"]


def test_a_tick_crosses_the_router_as_one_message_and_every_topic_reconciles(
    tmp_path: Path,
) -> None:
    raw, one_topic, robot = _run(tmp_path, "bundle_sensors = true\n")
    topics = robot["topics"]
    assert isinstance(topics, dict)
    sent = sum(t["sent"] for t in topics.values())
    assert sent > 200 and all(t["sent"] == t["received"] + t["lost"] for t in topics.values())
    assert robot["lost"] == 0, robot
    # machine1's six sensors at 50 Hz: one bundle a tick, so bundles far outnumber single
    # messages, and together they carried every sample the robot sent (plus hello and resends)
    bundles = raw.get(bundle.CHUNK, 0)
    singles = sum(n for key, n in raw.items() if key != bundle.CHUNK)
    assert bundles > 50 and bundles > 3 * singles, raw
    # a subscriber of one topic through arpz's transport saw that topic, and only it
    assert len(one_topic) >= 0.8 * topics["imu"]["sent"], (len(one_topic), topics)
    assert set(one_topic) == {"arpz/itest/robot/robot1/sensor/imu"}


def test_by_default_one_message_per_topic(tmp_path: Path) -> None:
    raw, _, robot = _run(tmp_path, "")
    assert bundle.CHUNK not in raw, raw
    assert robot["lost"] == 0 and robot["sent"] == robot["received"], robot


def test_heartbeats_through_a_router_never_announce_what_the_open_bundle_holds() -> None:
    """The writer's worker heartbeats (every 5 ms) while the tick that wrote holds the bundle
    (40 ms): the reader on another session, through a real router, must see no heartbeat
    announcing the held seq, so it sends no NACK and takes no duplicate. Before the writer
    asked its bundling publisher, a starved 25-robot fleet took 300-1 200 NACKs and as many
    duplicates a run (issue 17; the in-memory twin is in tests/unit/reliability)."""
    qos = QosProfile(heartbeat_period_s=0.005)
    topic = "arpz/itest/robot/r1/sensor/imu"
    heartbeats = HeldHeartbeats()

    with router() as (_, endpoint), client(endpoint) as robot, client(endpoint) as server:
        bundler = Bundler(robot, max_bytes=1280)
        reader = Reader(server, "arpz/itest/robot/r1/sensor/*", qos, on_data=lambda _p, _i: None)
        writer = Writer(bundler, topic, qos, block=False)
        watcher = server.subscribe(wire.heartbeat_key(topic, "*"), heartbeats)
        try:
            wait_until(
                lambda: writer.matched_count == 1 and reader.stats().matched == 1, what="matched"
            )
            for _ in range(5):
                with bundler.collect():
                    heartbeats.holding = writer.write(b"reading")
                    time.sleep(0.04)  # the writer's heartbeat timer fires several times
                    heartbeats.holding = 0
            wait_until(lambda: reader.stats().delivered == 5, what="5 samples delivered")
            wait_until(lambda: writer.acknowledged_through() == 5, what="5 acknowledged")
            during = heartbeats.during_holds()
            assert len(during) >= 5, heartbeats.seen  # heartbeats crossed during the holds
            assert all(last < held for held, last in during), during
            assert heartbeats.undecodable == 0
            assert (reader.stats().nacks, reader.stats().duplicates) == (0, 0), reader.stats()
            assert writer.stats().retransmitted == 0, writer.stats()
        finally:
            watcher.undeclare()
            writer.close()
            reader.close()
