"""The status page's server in process: a real Ingest fed samples, a StatusReader over it, and
HTTP requests to a real socket (no Zenoh; tests/integration/test_web_status.py runs a fleet)."""

from __future__ import annotations

import json
import socket
import urllib.error
import urllib.request

import msgspec
import pytest
from prometheus_client.parser import text_string_to_metric_families

from arpz.ceddp.cache_control import CacheControl
from arpz.ceddp.control import RobotRecord
from arpz.ceddp.ingest import Ingest
from arpz.ceddp.planner import Planner
from arpz.ceddp.status import FleetStatus, RateWindow, StatusReader
from arpz.ceddp.web import PAGE, StatusWeb
from arpz.core import keys
from arpz.core.config import CeddpConfig
from arpz.core.errors import ConfigError
from arpz.core.frames import MetricsFrame
from arpz.core.messages import Announce, RobotStats, Sample, TopicCounters, TopicInfo, encode
from tests.support import free_port

FLEET = "webtest"


def fed_ingest() -> tuple[Ingest, dict[str, RobotRecord]]:
    """r1 sends lidar seqs 1..10 without 4 and 5 (2 lost); r2 sends imu 1..3."""
    ingest = Ingest(FLEET, Planner(), CacheControl())
    for robot, topic, seqs in (("r1", "lidar", [1, 2, 3, *range(6, 11)]), ("r2", "imu", [1, 2, 3])):
        key = keys.sensor_key(FLEET, robot, topic)
        for seq in seqs:
            sample = Sample(f"{robot}-w", seq, 1_000 + seq, float(seq))
            ingest.handle_sensor(key, encode(sample), 2_000_000 + seq)
    stats = RobotStats(
        robot="r1",
        incarnation="i1",
        stamp_ns=1,
        final=False,
        topics={"lidar": TopicCounters(sent=10, retransmitted=3, gapped=2, deadline_missed=1)},
        cpu_percent=12.5,
        qos_epoch=4,
        qos_rate_hz=20.0,
        qos_depth=7,
    )
    announce = Announce("r1", "i1", [TopicInfo("lidar", "lidar", 10.0, "float")], [])
    robots = {
        "r1": RobotRecord(alive=True, joins=1, stats=stats, announce=announce, mode="channel"),
        "r2": RobotRecord(alive=False, joins=1, leaves=1),
    }
    return ingest, robots


def reader(frame: MetricsFrame | None = None) -> StatusReader:
    ingest, robots = fed_ingest()
    return StatusReader(
        CeddpConfig(fleet=FLEET, rerun_web_port=9090, grpc_port=9876),
        ingest,
        robots,
        lambda: frame,
        processed=lambda: 11,
        channel=lambda: None,
        views_dropped=lambda: {"foxglove": 3},
    )


FRAME = MetricsFrame(
    123,
    {("r1", "lidar"): {"rate_hz": 9.5, "latency_ms_p50": 2.0, "latency_ms_p99": 8.0}},
    {
        "r1": {"clock_offset_ms": -1.5},
        "ceddp": {"cpu_percent": 40.0, "ingest_load": 0.25, "ingest_backlog_ms": 7.5},
    },
)


def test_the_status_reads_counters_now_and_figures_of_the_last_interval() -> None:
    status = reader(FRAME).read()
    assert [r.robot for r in status.robots] == ["r1", "r2"]
    r1, r2 = status.robots
    assert (r1.received, r1.lost, r1.loss_ratio) == (8, 2, 0.2)
    assert (r1.sent, r1.retransmitted, r1.gapped, r1.deadline_missed) == (10, 3, 2, 1)
    assert (r1.qos_epoch, r1.qos_rate_hz, r1.qos_depth) == (4, 20.0, 7)
    assert r1.alive and not r2.alive
    assert r1.clock_offset_ms == -1.5 and r1.clock_delay_ms is None
    assert r1.topics[0].kind == "lidar" and r2.topics[0].kind is None
    assert r1.topics[0].latency_ms_p99 == 8.0
    assert r2.topics[0].latency_ms_p99 is None  # no interval figure for it in the frame
    assert r1.rate_hz is None  # a rate needs an earlier read
    assert status.ceddp.cpu_percent == 40.0 and status.ceddp.processed == 11
    assert status.ceddp.ingest_backlog_ms == 7.5
    assert status.metrics_stamp_ns == 123


def test_rates_are_measured_between_reads() -> None:
    ingest, robots = fed_ingest()
    status = StatusReader(
        CeddpConfig(fleet=FLEET), ingest, robots, lambda: None, processed=int, channel=lambda: None
    )
    assert status.read().robots[0].topics[0].rate_hz is None
    key = keys.sensor_key(FLEET, "r1", "lidar")
    for seq in range(11, 16):
        ingest.handle_sensor(key, encode(Sample("r1-w", seq, seq, float(seq))), 3_000_000 + seq)
    rate = status.read().robots[0].topics[0].rate_hz
    assert rate is not None and rate > 0


def test_the_rate_window_keeps_one_read_older_than_the_window() -> None:
    window: RateWindow[str] = RateWindow(2.0)
    assert window.rates(0.0, {"a": (0, 0)}) == {}
    assert window.rates(1.0, {"a": (10, 100)}) == {"a": (10.0, 100.0)}
    assert window.rates(2.0, {"a": (20, 200), "b": (5, 5)}) == {"a": (10.0, 100.0)}
    # at 4 s the read of 2 s is the newest at least 2 s old: the base
    assert window.rates(4.0, {"a": (60, 600), "b": (9, 9)}) == {"a": (20.0, 200.0), "b": (2.0, 2.0)}


def test_before_the_first_interval_the_figures_are_absent_not_zero() -> None:
    status = reader(None).read()
    assert status.metrics_stamp_ns == 0
    assert status.robots[0].topics[0].rate_hz is None
    assert status.robots[0].received == 8


@pytest.fixture
def web():
    server = StatusWeb(reader(FRAME).read, host="127.0.0.1", port=free_port())
    server.start()
    try:
        yield server
    finally:
        server.close()


def get(web: StatusWeb, path: str) -> tuple[str, bytes]:
    with urllib.request.urlopen(f"http://127.0.0.1:{web.port}{path}", timeout=5) as response:
        return response.headers["Content-Type"], response.read()


def test_api_status_is_the_json_of_the_status(web: StatusWeb) -> None:
    content_type, body = get(web, "/api/status")
    assert content_type == "application/json"
    status = msgspec.json.decode(body, type=FleetStatus)
    assert [r.robot for r in status.robots] == ["r1", "r2"]
    assert json.loads(body)["robots"][0]["clock_delay_ms"] is None


def test_metrics_parse_and_match_the_status(web: StatusWeb) -> None:
    content_type, body = get(web, "/metrics")
    assert content_type.startswith("text/plain")
    families = {f.name: f for f in text_string_to_metric_families(body.decode())}
    received = families["arpz_samples_received"]  # the parser strips _total from counters
    assert received.type == "counter"
    values = {(s.labels["robot"], s.labels["topic"]): s.value for s in received.samples}
    assert values == {("r1", "lidar"): 8.0, ("r2", "imu"): 3.0}
    lost = {s.labels["robot"]: s.value for s in families["arpz_samples_lost"].samples}
    assert lost == {"r1": 2.0, "r2": 0.0}
    latency = {s.labels["quantile"]: s.value for s in families["arpz_latency_seconds"].samples}
    assert latency == {"0.5": 0.002, "0.99": 0.008}
    assert families["arpz_robot_clock_offset_seconds"].samples[0].value == -0.0015
    up = {s.labels["robot"]: s.value for s in families["arpz_robot_up"].samples}
    assert up == {"r1": 1.0, "r2": 0.0}
    assert families["arpz_ceddp_cpu_ratio"].samples[0].value == 0.4
    assert families["arpz_ceddp_ingest_backlog_seconds"].samples[0].value == 0.0075
    assert families["arpz_live_view_dropped"].samples[0].value == 3.0
    assert "process_cpu_seconds" in families
    for name in families:  # Prometheus conventions: one prefix, counters end in _total
        assert name.startswith(("arpz_", "process_")), name
    assert "arpz_samples_received_total{" in body.decode()


def test_the_page_is_self_contained(web: StatusWeb) -> None:
    content_type, body = get(web, "/")
    assert content_type.startswith("text/html")
    assert body == PAGE.encode()
    page = body.decode()
    assert "/api/status" in page and "setInterval(poll, 1000)" in page
    # nothing loaded from elsewhere: the server may have no network (links are not loads)
    for load in ("<script src", "<link", "@import", "url(", "<img", "<iframe", "cdn"):
        assert load not in page


def test_an_unknown_path_is_404(web: StatusWeb) -> None:
    with pytest.raises(urllib.error.HTTPError) as caught:
        get(web, "/nope")
    assert caught.value.code == 404
    caught.value.close()


def test_a_port_in_use_is_a_config_error_naming_web_port() -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        with pytest.raises(ConfigError, match=f"web_port {port}.*in use"):
            StatusWeb(reader().read, host="127.0.0.1", port=port)


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"web_port": 70000}, "web_port must be 0..65535"),
        ({"web_port": 8080, "foxglove_port": 8080}, "foxglove_port and web_port are both 8080"),
        ({"rerun_web_port": 9090}, "rerun_web_port needs grpc_port"),
        ({"foxglove_port": -1}, "foxglove_port must be 0..65535"),
    ],
)
def test_the_live_ports_are_validated(fields: dict[str, int], message: str) -> None:
    from arpz.core.config import from_dict

    with pytest.raises(ConfigError, match=message):
        from_dict(fields, CeddpConfig, source="test.toml")


def test_a_view_that_cannot_start_closes_the_ones_opened_before_it() -> None:
    from arpz.ceddp.server import CeddpServer
    from arpz.transport.memory import MemoryBus, MemoryTransport

    web_port = free_port()
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        config = CeddpConfig(fleet=FLEET, web_port=web_port, foxglove_port=busy.getsockname()[1])
        server = CeddpServer(config, MemoryTransport(MemoryBus()))
        with pytest.raises(ConfigError, match="foxglove_port"):
            server.start()
    with socket.socket() as again:  # the status page's port was let go
        again.bind(("127.0.0.1", web_port))
