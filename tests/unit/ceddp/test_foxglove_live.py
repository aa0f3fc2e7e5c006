"""The Foxglove view in process: readings in, a real WebSocket client out (tests/foxglove_ws.py).

No Zenoh here: the planner side is called directly, as the ingest calls it. The integration
test (tests/integration/test_foxglove_live.py) does the same against a running CEDDP.
"""

from __future__ import annotations

import json
import socket
import struct
import time

import numpy as np
import pytest

from arpz.ceddp.foxglove_live import FoxgloveLive, json_schema, to_json
from arpz.ceddp.planner import Reading
from arpz.core.errors import ConfigError
from arpz.core.frames import MetricsFrame
from arpz.core.rosmsg.convert import to_ros
from tests.foxglove_ws import FoxgloveClient, descriptor_fields, packed_doubles, protobuf_fields
from tests.support import free_port, wait_until

KINDS = {"lidar": "lidar", "imu": "imu", "cam": "camera", "cloud": "pointcloud", "pir": "pir"}


def reading(topic: str, value: object, seq: int = 1) -> Reading:
    stamp = 1_700_000_000_000_000_000 + seq
    return Reading("r1", topic, value, stamp, stamp + 1000, seq)  # type: ignore[arg-type]


@pytest.fixture
def live():
    view = FoxgloveLive(
        host="127.0.0.1", port=free_port(), kind_of=lambda robot, topic: KINDS.get(topic)
    )
    view.start()
    try:
        yield view
    finally:
        view.stop()


def test_a_client_receives_every_kind_in_its_schema(live: FoxgloveLive) -> None:
    frame = np.arange(160 * 120 * 3, dtype=np.uint8).tobytes()  # 160 x 120 RGB
    cloud = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], dtype="<f4").tobytes()
    firsts = [
        reading("lidar", 1.25),
        reading("imu", 9.81),
        reading("cam", frame),
        reading("cloud", cloud),
        reading("pir", "detect"),
    ]
    for r in firsts:
        live.on_reading(r)
    live.on_metrics(MetricsFrame(5, {("r1", "lidar"): {"rate_hz": 10.0}}, {"r1": {"cpu": 1.0}}))
    with FoxgloveClient("127.0.0.1", live.port) as client:
        topics = {"/r1/lidar", "/r1/imu", "/r1/cam", "/r1/cloud", "/r1/pir", "/r1/metrics"}
        channels = client.wait_for_topics(topics, timeout_s=5)
        assert channels["/r1/lidar"]["schemaName"] == "foxglove.LaserScan"
        assert channels["/r1/lidar"]["encoding"] == "protobuf"
        assert channels["/r1/cam"]["schemaName"] == "foxglove.RawImage"
        assert channels["/r1/cloud"]["schemaName"] == "foxglove.PointCloud"
        assert channels["/r1/imu"]["schemaName"] == "sensor_msgs/msg/Imu"
        assert channels["/r1/imu"]["encoding"] == "json"
        assert channels["/r1/pir"]["schemaName"] == "std_msgs/msg/Bool"
        subs = client.subscribe([int(channels[t]["id"]) for t in sorted(topics)])
        by_sub = {s: channels_topic(channels, c) for s, c in subs.items()}
        wait_until(lambda: all_subscribed(live), timeout_s=5, what="subscriptions")
        for r in [
            reading("lidar", 2.5, 2),
            reading("imu", 0.5, 2),
            reading("cam", frame, 2),
            reading("cloud", cloud, 2),
            reading("pir", "not detect", 2),
        ]:
            live.on_reading(r)
        live.on_metrics(MetricsFrame(6, {("r1", "lidar"): {"rate_hz": 12.0}}, {"r1": {}}))
        got: dict[str, bytes] = {}
        deadline = time.monotonic() + 5
        while set(got) != topics and time.monotonic() < deadline:
            message = client.poll(deadline)
            if message is not None:
                got[by_sub[message.subscription]] = message.payload
        assert set(got) == topics

        scan_fields = descriptor_fields(channels["/r1/lidar"]["schema"], "LaserScan")
        scan = protobuf_fields(got["/r1/lidar"])
        assert packed_doubles(scan[scan_fields["ranges"]][0]) == [2.5]
        assert scan[scan_fields["frame_id"]] == [b"r1/lidar"]

        image_fields = descriptor_fields(channels["/r1/cam"]["schema"], "RawImage")
        image = protobuf_fields(got["/r1/cam"])
        assert uint32(image[image_fields["width"]][0]) == 160  # fixed32 in the schema
        assert uint32(image[image_fields["height"]][0]) == 120
        assert image[image_fields["encoding"]] == [b"rgb8"]
        assert image[image_fields["data"]] == [frame]

        cloud_fields = descriptor_fields(channels["/r1/cloud"]["schema"], "PointCloud")
        points = protobuf_fields(got["/r1/cloud"])
        assert uint32(points[cloud_fields["point_stride"]][0]) == 12
        assert list(struct.iter_unpack("<3f", points[cloud_fields["data"]][0])) == [
            (1.0, 2.0, 3.0),
            (4.0, 5.0, 6.0),
        ]

        imu = json.loads(got["/r1/imu"])
        assert imu["linear_acceleration"]["z"] == 0.5
        assert imu["header"]["stamp"] == {"sec": 1_700_000_000, "nanosec": 2}
        assert json.loads(got["/r1/pir"]) == {"data": False}
        assert json.loads(got["/r1/metrics"])["topics"]["lidar"]["rate_hz"] == 12.0
    assert live.dropped == 0
    assert live.unshowable == 0


def uint32(raw: bytes) -> int:
    return int(struct.unpack("<I", raw)[0])


def channels_topic(channels: dict[str, dict[str, object]], channel_id: int) -> str:
    return next(t for t, c in channels.items() if c["id"] == channel_id)


def all_subscribed(live: FoxgloveLive) -> bool:
    return all(t.channel.has_sinks() for t in live._topics.values())


def test_a_full_queue_drops_and_counts_and_never_blocks() -> None:
    view = FoxgloveLive(
        host="127.0.0.1", port=free_port(), kind_of=lambda r, t: "lidar", queue_limit=10
    )
    try:  # not started: nothing takes from the queue
        started = time.perf_counter()
        for seq in range(1, 1001):
            view.on_reading(reading("lidar", 1.0, seq))
        elapsed = time.perf_counter() - started
        assert view.dropped == 990
        assert elapsed < 0.5  # a put that cannot wait: 1000 offers are quick
    finally:
        view.stop()


def test_unannounced_and_unshowable_readings_are_counted(live: FoxgloveLive) -> None:
    live.on_reading(Reading("r1", "mystery", 1.0, 1, 2, 1))
    live.on_reading(reading("cam", b"\x00" * 10))  # not whole RGB pixels
    with FoxgloveClient("127.0.0.1", live.port) as client:
        channels = client.wait_for_topics({"/r1/cam"}, timeout_s=5)
        client.subscribe([int(channels["/r1/cam"]["id"])])
        wait_until(lambda: all_subscribed(live), timeout_s=5, what="subscription")
        live.on_reading(reading("cam", b"\x00" * 10, 2))
        wait_until(lambda: live.unshowable == 1, timeout_s=5, what="unshowable counted")
    assert live.unannounced == 1


def test_a_port_in_use_is_a_config_error_naming_the_setting() -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        with pytest.raises(ConfigError, match="foxglove_port"):
            FoxgloveLive(host="127.0.0.1", port=port, kind_of=lambda r, t: None)


def test_ros_messages_become_json_with_a_matching_schema() -> None:
    message = to_json(to_ros("lidar", float("nan"), stamp_ns=3, frame_id="r/l"))
    assert message["ranges"] == [None]  # JSON has no NaN
    schema = json_schema("sensor_msgs/msg/LaserScan", message)
    assert schema["title"] == "sensor_msgs/msg/LaserScan"
    assert schema["properties"]["header"]["properties"]["frame_id"] == {"type": "string"}


def test_an_advertised_topic_nobody_subscribes_to_is_not_queued(live: FoxgloveLive) -> None:
    live.on_reading(reading("lidar", 1.0))
    wait_until(lambda: ("r1", "lidar") in live._topics, timeout_s=5, what="channel advertised")
    for seq in range(2, 5000):
        live.on_reading(reading("lidar", 1.0, seq))
    assert live.dropped == 0 and live._queue.qsize() == 0
