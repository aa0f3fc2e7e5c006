"""The live Foxglove view of a fleet (``foxglove_port``): every robot's sensor topics with
standard types, and the CEDDP's metrics, on a Foxglove WebSocket server (foxglove-sdk).

``FoxgloveLive`` is a planner: the ingest hands it each reading cache control let through
(every change of a topic's value), as it hands them to every planner. It only puts
the reading in a bounded queue; a full queue drops the reading and counts it (``dropped``), so a
slow viewer never slows the ingest. Once a topic's channel is advertised, its readings are
queued only while some client subscribes to it. One worker thread converts and logs. The metrics
ticker hands it each interval's ``MetricsFrame`` the same way.

Channels (docs/tools.md "Live views"): ``/{robot}/{topic}`` per sensor topic and
``/{robot}/metrics`` per robot, ``/ceddp/metrics`` for the CEDDP. Foxglove's own schemas where
one fits the sensor kind, so its 3D and Image panels draw them unconfigured: LIDAR as
``foxglove.LaserScan`` (one beam, at angle 0), camera as ``foxglove.RawImage`` (rgb8), point
cloud as ``foxglove.PointCloud`` (float32 x, y, z). The other kinds go on JSON channels whose
JSON schema is named after, and has the fields of, the ROS 2 message a ROS user knows
(``sensor_msgs/msg/Imu``, ``Range``, ``Temperature``, ``Illuminance``, ``std_msgs/msg/Bool`` for
flame and PIR). Metrics are JSON.

This is the only module of arpz that imports foxglove (an import-linter contract).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import queue
import threading
from collections.abc import Callable
from typing import Any

import foxglove
import msgspec
import numpy as np
from foxglove.channels import LaserScanChannel, PointCloudChannel, RawImageChannel
from foxglove.messages import (
    LaserScan,
    PackedElementField,
    PackedElementFieldNumericType,
    PointCloud,
    RawImage,
    Timestamp,
)

from arpz.ceddp.planner import Planner, Reading
from arpz.core.errors import ConfigError
from arpz.core.frames import MetricsFrame
from arpz.core.msgtypes import as_dict
from arpz.core.rosmsg.convert import ConversionError, camera_size, to_ros
from arpz.core.rosmsg.types import ROS_TYPES
from arpz.core.throttled_log import ThrottledLog

log = logging.getLogger(__name__)
throttled = ThrottledLog(log)

_STOP = object()


def _timestamp(stamp_ns: int) -> Timestamp:
    return Timestamp(sec=stamp_ns // 1_000_000_000, nsec=stamp_ns % 1_000_000_000)


def to_json(value: Any) -> Any:
    """A ROS 2 message of ``arpz.core.rosmsg`` (rosbags dataclasses, numpy arrays) as JSON values:
    fields by name, arrays as lists, NaN and infinities as null (JSON has none)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {
            f.name: to_json(getattr(value, f.name))
            for f in dataclasses.fields(value)
            if not f.name.startswith("__")
        }
    if isinstance(value, np.ndarray):
        return [to_json(v) for v in value.tolist()]
    if isinstance(value, list | tuple):
        return [to_json(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def json_schema(title: str, example: Any) -> dict[str, Any]:
    """The JSON schema of messages shaped as ``example`` (one message of the type)."""
    schema = _schema_of(example)
    return {"title": title, **schema}


def _schema_of(value: Any) -> dict[str, Any]:
    if isinstance(value, dict):
        return {"type": "object", "properties": {k: _schema_of(v) for k, v in value.items()}}
    if isinstance(value, list):
        return {"type": "array", "items": _schema_of(value[0]) if value else {}}
    if isinstance(value, bool):
        return {"type": "boolean"}
    if isinstance(value, int):
        return {"type": "integer"}
    if isinstance(value, float) or value is None:
        return {"type": ["number", "null"]}
    return {"type": "string"}


#: the metrics channels' schema: numbers per metric name (docs/tools.md "Live views" lists them)
METRICS_SCHEMA: dict[str, Any] = {
    "title": "arpz/Metrics",
    "type": "object",
    "properties": {
        "stamp_ns": {"type": "integer"},
        "topics": {"type": "object", "additionalProperties": {"type": "object"}},
    },
    "additionalProperties": {"type": ["number", "null"]},
}
#: kinds arpz.core.rosmsg does not know (a custom driver's): the value as it is
VALUE_TYPE = "arpz/Value"


class _Topic:
    """One sensor topic's channel, made at its first reading, and how to turn a reading into
    its message: Foxglove's own schema for LIDAR, camera and point cloud, otherwise the ROS 2
    message of ``arpz.core.rosmsg`` as JSON."""

    def __init__(self, topic: str, kind: str, first: Reading, context: foxglove.Context) -> None:
        self.kind = kind
        self.channel: Any
        if kind == "lidar":
            self.channel = LaserScanChannel(topic, context=context)
        elif kind == "camera":
            self.channel = RawImageChannel(topic, context=context)
        elif kind == "pointcloud":
            self.channel = PointCloudChannel(topic, context=context)
        else:
            title = ROS_TYPES[kind][0] if kind in ROS_TYPES else VALUE_TYPE
            example = self.message(first, topic.strip("/"))
            schema = json_schema(title, example if example is not None else {})
            self.channel = foxglove.Channel(topic, schema=schema, context=context)

    def message(self, reading: Reading, frame_id: str) -> Any:
        """The message of ``reading``; None if it cannot be shown as its kind (counted)."""
        value, stamp = reading.value, reading.stamp_ns
        if self.kind == "lidar":
            if not isinstance(value, float):
                return None
            return LaserScan(
                timestamp=_timestamp(stamp),
                frame_id=frame_id,
                start_angle=0.0,
                end_angle=0.0,
                ranges=[value],
                intensities=[],
            )
        if self.kind == "camera":
            if not isinstance(value, bytes):
                return None
            try:
                width, height = camera_size(len(value))
            except ConversionError:
                return None
            return RawImage(
                timestamp=_timestamp(stamp),
                frame_id=frame_id,
                width=width,
                height=height,
                encoding="rgb8",
                step=width * 3,
                data=value,
            )
        if self.kind == "pointcloud":
            if not isinstance(value, bytes) or len(value) % 12:
                return None
            f32 = PackedElementFieldNumericType.Float32
            return PointCloud(
                timestamp=_timestamp(stamp),
                frame_id=frame_id,
                point_stride=12,
                fields=[
                    PackedElementField(name=axis, offset=4 * i, type=f32)
                    for i, axis in enumerate("xyz")
                ],
                data=value,
            )
        if isinstance(value, msgspec.Struct):  # a typed topic's message, as JSON
            return as_dict(value)
        if self.kind not in ROS_TYPES:
            return None if isinstance(value, bytes) else {"stamp_ns": stamp, "value": value}
        try:
            return to_json(to_ros(self.kind, value, stamp_ns=stamp, frame_id=frame_id))
        except ConversionError:
            return None


class FoxgloveLive(Planner):
    """A Foxglove WebSocket server on ``host:port`` fed from the ingest and the metrics ticker.

    ``kind_of(robot, topic)`` is the sensor kind the robot announced (None until it did: such
    readings are counted in ``unannounced`` and not shown). The port is bound here, so a port in
    use fails the CEDDP's start with a ConfigError naming ``foxglove_port``."""

    def __init__(
        self,
        *,
        host: str,
        port: int,
        kind_of: Callable[[str, str], str | None],
        queue_limit: int = 2048,
        name: str = "arpz CEDDP",
    ) -> None:
        self._kind_of = kind_of
        self._context = foxglove.Context()
        try:
            self._server = foxglove.start_server(
                name=name, host=host, port=port, context=self._context
            )
        except Exception as exc:  # foxglove raises its own error type for a failed bind
            raise ConfigError(
                f"foxglove_port {port} on {host} cannot be served: {exc}; choose another "
                "foxglove_port (or 0 to turn the Foxglove view off)"
            ) from None
        self.port = int(self._server.port)
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=queue_limit)
        #: readings and frames the full queue refused (the viewer fell behind the fleet)
        self.dropped = 0
        #: readings of topics whose kind the robot has not announced yet (not shown)
        self.unannounced = 0
        #: readings that cannot be shown as their kind (a camera frame of unknown size, ...)
        self.unshowable = 0
        #: messages logged to subscribed channels
        self.logged = 0
        self._topics: dict[tuple[str, str], _Topic] = {}
        self._metrics: dict[str, foxglove.Channel] = {}
        self._thread = threading.Thread(target=self._run, name="arpz-foxglove", daemon=True)

    # -- the ingest's and the ticker's side: never blocks -------------------------------------

    def on_reading(self, reading: Reading) -> None:
        topic = self._topics.get((reading.robot, reading.topic))
        if topic is not None and not topic.channel.has_sinks():
            return  # advertised, and nobody subscribed: nothing to show, nothing to queue
        self._offer(reading)

    def on_metrics(self, frame: MetricsFrame) -> None:
        self._offer(frame)

    def _offer(self, item: Reading | MetricsFrame) -> None:
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            self.dropped += 1

    def counters(self) -> dict[str, int]:
        return {
            "dropped": self.dropped,
            "unannounced": self.unannounced,
            "unshowable": self.unshowable,
            "logged": self.logged,
        }

    # -- life cycle ---------------------------------------------------------------------------

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        """Stop the worker (what is queued is dropped: a viewer needs no backlog) and the
        server, closing every client's connection."""
        if self._thread.is_alive():
            while True:
                try:
                    self._queue.put(_STOP, timeout=0.1)
                    break
                except queue.Full:
                    self._drain_one()
            self._thread.join(timeout=10)
        self._server.stop()

    def _drain_one(self) -> None:
        with contextlib.suppress(queue.Empty):
            self._queue.get_nowait()

    # -- the worker ---------------------------------------------------------------------------

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is _STOP:
                return
            try:
                if isinstance(item, MetricsFrame):
                    self._log_metrics(item)
                else:
                    self._log_reading(item)
            except Exception:  # a bad value or a viewer failure must not stop the view
                throttled.exception("foxglove log", "Foxglove logging failed")

    def _log_reading(self, reading: Reading) -> None:
        slot = (reading.robot, reading.topic)
        topic = self._topics.get(slot)
        if topic is None:
            kind = self._kind_of(*slot)
            if kind is None:
                self.unannounced += 1
                return
            topic = self._topics[slot] = _Topic(
                f"/{reading.robot}/{reading.topic}", kind, reading, self._context
            )
        if not topic.channel.has_sinks():
            return
        message = topic.message(reading, f"{reading.robot}/{reading.topic}")
        if message is None:
            self.unshowable += 1
            throttled.warning(
                f"foxglove {topic.kind}",
                "a %s reading of %d bytes on %s/%s cannot be shown in Foxglove (%d so far)",
                topic.kind,
                len(reading.value) if isinstance(reading.value, bytes) else 0,
                reading.robot,
                reading.topic,
                self.unshowable,
            )
            return
        topic.channel.log(message, log_time=reading.stamp_ns)
        self.logged += 1

    def _log_metrics(self, frame: MetricsFrame) -> None:
        rows: dict[str, dict[str, Any]] = {
            robot: {"stamp_ns": frame.stamp_ns, **_finite(row)}
            for robot, row in frame.robots.items()
        }
        for (robot, topic), row in frame.topics.items():
            rows.setdefault(robot, {"stamp_ns": frame.stamp_ns}).setdefault("topics", {})[topic] = (
                _finite(row)
            )
        for robot, message in rows.items():
            channel = self._metrics.get(robot)
            if channel is None:
                channel = self._metrics[robot] = foxglove.Channel(
                    f"/{robot}/metrics", schema=METRICS_SCHEMA, context=self._context
                )
            if channel.has_sinks():
                channel.log(message, log_time=frame.stamp_ns)
                self.logged += 1


def _finite(row: dict[str, float]) -> dict[str, float | None]:
    """JSON has no NaN or infinity: such a value is sent as null."""
    return {k: (v if math.isfinite(v) else None) for k, v in row.items()}
