"""The layout of an arpz recording: what ``arpz record`` writes and ``arpz play`` reads.

An MCAP file with the rosbag2 profile (``ros2``): one channel per arpz key. A sensor topic of a
kind with a standard ROS 2 type (arpz.core.rosmsg) is a ``cdr`` channel whose schema is the full
``ros2msg`` definition, so ROS 2 tools, Foxglove and any MCAP reader decode it. Everything else
(commands, the Hello probe, the robots' reports, their liveliness tokens) keeps arpz's own
msgpack payload on a schemaless ``msgpack`` channel (MCAP's well-known encoding for it; the
layout is arpz's, named by the channel's ``arpz_type`` metadata and documented in
docs/protocol.md). Channel metadata: ``arpz_key`` (the Zenoh key), ``arpz_kind``, ``arpz_type``,
``arpz_qos`` (arpz's QoS profile as JSON, or ``none`` for plain keys) and rosbag2's
``offered_qos_profiles`` (YAML). docs/tools.md "Recording and replay" describes it for users.
"""

from __future__ import annotations

import fnmatch
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, Final

import msgspec
from mcap.writer import CompressionType, Writer

from arpz.core import keys
from arpz.core.config import SENSOR_KINDS
from arpz.core.protocol.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    LivelinessPolicy,
    QosProfile,
    ReliabilityPolicy,
)
from arpz.core.rosmsg.convert import message_definition
from arpz.core.rosmsg.types import ros_type_for
from arpz.core.transport import SessionSettings
from arpz.transport.zenoh import ZenohTransport

PROFILE: Final = "ros2"
CDR: Final = "cdr"
MSGPACK: Final = "msgpack"
#: chunks are compressed with zstd: the mcap library's default, and readable by rosbag2,
#: Foxglove, rosbags and mcap-ros2-support alike
COMPRESSION: Final = CompressionType.ZSTD
#: the MCAP metadata record that says which fleet was recorded, and how
METADATA_NAME: Final = "arpz"

#: channel kinds beyond the sensor kinds, with the arpz type of their msgpack payload
ARPZ_TYPES: Final = {
    "hello": "arpz.core.messages.Hello",
    "command": "arpz.core.messages.Command",
    "telemetry": "arpz.core.messages.Telemetry",
    "announce": "arpz.core.messages.Announce",
    "stats": "arpz.core.messages.RobotStats",
    "qos_ack": "arpz.core.messages.QosAck",
    #: a liveliness token appearing (true) or vanishing (false)
    "liveliness": "bool",
    #: a sensor topic no announcement named the kind of (recorded as it came)
    "sample": "arpz.core.messages.Sample",
}
_REPORTS: Final = {
    "telemetry": "telemetry",
    "announce": "announce",
    "stats": "stats",
    "qos": "qos_ack",
}


@dataclass(frozen=True)
class Topic:
    """One recorded key: where it goes in the MCAP file and how its payload is written."""

    key: str
    robot: str
    #: a sensor kind (lidar, camera, ...) or one of ARPZ_TYPES
    kind: str
    #: the reliable channel's profile of the key (None: a plain key)
    qos: QosProfile | None

    @property
    def name(self) -> str:
        """The MCAP topic, ROS 2 style: ``/robot1/lidar_0``, ``/robot1/cmd/velocity``, and
        ``/robot1/arpz/announce`` for arpz's own reports and tokens (a sensor name is one key
        chunk, so neither can clash with a sensor topic)."""
        parsed = keys.parse_robot_key(self.key)
        assert parsed is not None, self.key
        robot, what, name = parsed
        if what in ("sensor", "frames"):
            return f"/{robot}/{name}"
        if what == "cmd":
            return f"/{robot}/cmd/{name}"
        return f"/{robot}/arpz/{what}" + (f"/{name}" if name else "")

    @property
    def standard(self) -> bool:
        """Written as a ROS 2 message (CDR), not as arpz msgpack."""
        return self.kind in SENSOR_KINDS

    @property
    def type_name(self) -> str:
        return ros_type_for(self.kind) if self.standard else ARPZ_TYPES[self.kind]

    def metadata(self) -> dict[str, str]:
        return {
            "arpz_key": self.key,
            "arpz_kind": self.kind,
            "arpz_type": self.type_name,
            "arpz_qos": msgspec.json.encode(self.qos).decode() if self.qos else "none",
            "offered_qos_profiles": offered_qos_yaml(self.qos),
        }


def matches(topic: Topic, patterns: Sequence[str]) -> bool:
    """A topic selected by shell patterns on its MCAP topic or its arpz key (no patterns: all)."""
    return not patterns or any(
        fnmatch.fnmatchcase(topic.name, p) or fnmatch.fnmatchcase(topic.key, p) for p in patterns
    )


def open_client(endpoints: Sequence[str], zenoh_config: str | None) -> ZenohTransport:
    """A client session to the fleet's router, as a robot opens one (trying for 5 s)."""
    settings = SessionSettings(mode="client", connect=endpoints, config_file=zenoh_config)
    return ZenohTransport.open(settings, timeout_s=5.0)


def report_kind(what: str) -> str | None:
    """The channel kind of a robot report key's last chunk (``stats``...), None if not one."""
    return _REPORTS.get(what)


def _duration(seconds: float) -> str:
    if seconds <= 0 or not math.isfinite(seconds):  # arpz's 0 = none: rmw's infinite
        return "sec: 2147483647\n    nsec: 4294967295"
    sec = int(seconds)
    return f"sec: {sec}\n    nsec: {round((seconds - sec) * 1e9)}"


def offered_qos_yaml(qos: QosProfile | None) -> str:
    """rosbag2's ``offered_qos_profiles`` of a key (the rmw enum values of ROS 2 Humble); a plain
    key is recorded as BEST_EFFORT VOLATILE, which is what plain Zenoh gives."""
    qos = qos or QosProfile(reliability=ReliabilityPolicy.BEST_EFFORT)
    history = 1 if qos.history is HistoryPolicy.KEEP_LAST else 2
    reliability = 1 if qos.reliability is ReliabilityPolicy.RELIABLE else 2
    durability = 1 if qos.durability is DurabilityPolicy.TRANSIENT_LOCAL else 2
    liveliness = 1 if qos.liveliness is LivelinessPolicy.AUTOMATIC else 3
    depth = qos.depth if qos.history is HistoryPolicy.KEEP_LAST else 0
    return (
        f"- history: {history}\n  depth: {depth}\n  reliability: {reliability}\n"
        f"  durability: {durability}\n  deadline:\n    {_duration(qos.deadline_s)}\n"
        f"  lifespan:\n    {_duration(qos.lifespan_s)}\n  liveliness: {liveliness}\n"
        f"  liveliness_lease_duration:\n    {_duration(qos.lease_duration_s)}\n"
        "  avoid_ros_namespace_conventions: false\n"
    )


def split_path(out: Path, index: int, splitting: bool) -> Path:
    """``out`` itself, or ``{stem}_{index}.mcap`` beside it when the recording is split (the
    naming rosbag2 uses for its own splits: ``my_bag_0.mcap``, ``my_bag_1.mcap``, ...)."""
    return out.with_name(f"{out.stem}_{index}{out.suffix}") if splitting else out


class McapSink:
    """Writes messages into one MCAP file after another, starting the next one when the current
    one has reached ``split_bytes`` (it may pass it by one chunk) or holds ``split_s`` of log
    time (0: never). Every file is whole on its
    own: each repeats the schemas and channels of the topics it holds. Not thread-safe: one
    writer thread owns it."""

    def __init__(
        self, out: Path, *, split_bytes: int, split_s: float, metadata: dict[str, str]
    ) -> None:
        self.out = out
        self.split_bytes = split_bytes
        self.split_ns = int(split_s * 1e9)
        self.metadata = metadata
        self.files: list[Path] = []
        self._stream: BinaryIO | None = None
        self._writer: Writer | None = None
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._first_ns: int | None = None

    @property
    def splitting(self) -> bool:
        return self.split_bytes > 0 or self.split_ns > 0

    def _open(self) -> Writer:
        path = split_path(self.out, len(self.files), self.splitting)
        path.parent.mkdir(parents=True, exist_ok=True)
        self._stream = path.open("wb")
        # the file grows a chunk at a time: with a size limit, chunks of an eighth of it keep
        # each file within one chunk of the limit
        chunk = max(4096, min(2**20, self.split_bytes // 8)) if self.split_bytes else 2**20
        self._writer = Writer(self._stream, chunk_size=chunk, compression=COMPRESSION)
        self._writer.start(profile=PROFILE, library="arpz record")
        self._writer.add_metadata(METADATA_NAME, self.metadata)
        self._channels, self._schemas, self._first_ns = {}, {}, None
        self.files.append(path)
        return self._writer

    def _due(self, log_ns: int) -> bool:
        assert self._stream is not None
        if self.split_bytes and self._stream.tell() >= self.split_bytes:
            return True
        return bool(
            self.split_ns
            and self._first_ns is not None
            and log_ns - self._first_ns >= self.split_ns
        )

    def _channel(self, writer: Writer, topic: Topic) -> int:
        channel = self._channels.get(topic.key)
        if channel is not None:
            return channel
        schema = 0
        if topic.standard:
            schema = self._schemas.get(topic.type_name, 0)
            if not schema:
                schema = writer.register_schema(
                    topic.type_name, "ros2msg", message_definition(topic.type_name).encode()
                )
                self._schemas[topic.type_name] = schema
        channel = writer.register_channel(
            topic.name, CDR if topic.standard else MSGPACK, schema, topic.metadata()
        )
        self._channels[topic.key] = channel
        return channel

    def write(
        self, topic: Topic, data: bytes, *, log_ns: int, publish_ns: int, sequence: int
    ) -> None:
        writer = self._writer
        if writer is None or self._due(log_ns):
            self.close()
            writer = self._open()
        if self._first_ns is None:
            self._first_ns = log_ns
        writer.add_message(
            self._channel(writer, topic),
            log_time=log_ns,
            data=data,
            publish_time=publish_ns,
            sequence=sequence & 0xFFFFFFFF,
        )

    def finish(self) -> list[Path]:
        """Close the last file (an empty recording still gives one valid file); the files."""
        if not self.files:
            self._open()
        self.close()
        return self.files

    def close(self) -> None:
        if self._writer is not None:
            self._writer.finish()  # type: ignore[no-untyped-call]
            self._writer = None
        if self._stream is not None:
            self._stream.close()
            self._stream = None

    def __enter__(self) -> McapSink:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
