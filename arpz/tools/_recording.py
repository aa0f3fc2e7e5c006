"""The layout of an arpz recording: what ``arpz record`` writes and ``arpz play`` reads.

An MCAP file with the rosbag2 profile (``ros2``): one channel per arpz key, and by default every
channel one that standard ROS 2 tooling reads (``ros2 bag``, rosbags, mcap-ros2-support,
Foxglove): a ``cdr`` channel whose schema is the full ``ros2msg`` definition of a standard type.

- A sensor topic of a kind with a standard ROS 2 type (arpz.core.rosmsg.types) is that type.
- A command is the standard type of its value (arpz.core.rosmsg.commands: ``[v, omega]`` a
  ``geometry_msgs/msg/Twist``), decided by the first command of the channel.
- A robot's reports (announce, stats, QoS ack, telemetry) and its presence and mode tokens are
  ``diagnostic_msgs/msg/DiagnosticArray`` whose key/value pairs are the message's fields
  (arpz.core.rosmsg.reports: exact, so ``play`` turns them back into what the robot sent).
- arpz's own messages that have no standard type (the Hello probe, and sensor samples whose kind
  no announcement named) are left out, and counted; with ``--include-internal`` they are kept as
  schemaless ``json`` channels (MCAP's well-known encoding: the mcap library, Foxglove and any
  JSON reader take them; ROS 2 tools skip them), their JSON Schema in the channel metadata.

Recordings made before (issue 41) kept everything but the sensor topics as arpz's msgpack on
schemaless ``msgpack`` channels; ``play`` still reads them. Channel metadata: ``arpz_key`` (the
Zenoh key), ``arpz_kind``, ``arpz_type`` (the channel's type), ``arpz_message`` (the arpz
message each message is, once converted back), ``arpz_qos`` (arpz's QoS profile as JSON, or
``none`` for plain keys) and rosbag2's ``offered_qos_profiles`` (YAML). docs/tools.md
"Recording and replay" describes it for users.
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
from arpz.core.config import LARGE_KINDS, LARGE_TYPES, MESSAGE_KIND, SENSOR_KINDS
from arpz.core.messages import (
    DECODE_ERRORS,
    Announce,
    Command,
    Hello,
    LargeSample,
    MessageSample,
    QosAck,
    RobotStats,
    Sample,
    Telemetry,
)
from arpz.core.protocol.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    LivelinessPolicy,
    QosProfile,
    ReliabilityPolicy,
)
from arpz.core.rosmsg.convert import ConversionError, message_definition, serialize
from arpz.core.rosmsg.reports import (
    DIAGNOSTIC_ARRAY,
    OK,
    STALE,
    from_fields,
    message_from_cdr,
    report_from_cdr,
    report_to_ros,
    to_fields,
)
from arpz.core.rosmsg.types import ros_type_for
from arpz.core.transport import SessionSettings
from arpz.transport.zenoh import ZenohTransport

PROFILE: Final = "ros2"
CDR: Final = "cdr"
JSON: Final = "json"
#: the message encoding of everything but the sensor topics in recordings made before issue 41
MSGPACK: Final = "msgpack"
#: chunks are compressed with zstd: the mcap library's default, and readable by rosbag2,
#: Foxglove, rosbags and mcap-ros2-support alike
COMPRESSION: Final = CompressionType.ZSTD
#: the MCAP metadata record that says which fleet was recorded, and how
METADATA_NAME: Final = "arpz"

LIVELINESS: Final = "liveliness"
#: a robot's reports, written as DiagnosticArray: channel kind -> its arpz message
REPORT_MESSAGES: Final[dict[str, type[msgspec.Struct]]] = {
    "announce": Announce,
    "stats": RobotStats,
    "qos_ack": QosAck,
    "telemetry": Telemetry,
}
#: arpz's own messages with no standard ROS 2 type: channel kind -> its arpz message. Left out
#: by default; JSON with ``--include-internal``. ``sample`` / ``large_sample``: a sensor topic
#: whose kind no announcement named; ``command``: in recordings made before issue 41 only
INTERNAL_MESSAGES: Final[dict[str, type[msgspec.Struct]]] = {
    "hello": Hello,
    "sample": Sample,
    "large_sample": LargeSample,
    "command": Command,
}
_REPORTS: Final = {
    "telemetry": "telemetry",
    "announce": "announce",
    "stats": "stats",
    "qos": "qos_ack",
}


def _message_name(message_type: type[msgspec.Struct]) -> str:
    return f"arpz.core.messages.{message_type.__name__}"


@dataclass(frozen=True)
class Topic:
    """One recorded key: where it goes in the MCAP file and how its messages are written."""

    key: str
    robot: str
    #: a sensor kind (lidar, camera, ...), ``command``, ``liveliness``, or a kind of
    #: REPORT_MESSAGES or INTERNAL_MESSAGES
    kind: str
    #: the reliable channel's profile of the key (None: a plain key)
    qos: QosProfile | None
    #: a command channel's ROS 2 type (of its first command; arpz.core.rosmsg.commands)
    command_type: str | None = None
    #: a typed sensor's ROS 2 message type (kind "message"), and its ``.msg`` definition as
    #: rosbag2 stores it (the recorder's message types give it: a team's own types too)
    msg_type: str | None = None
    definition: str = ""

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
    def sensor(self) -> bool:
        """A sensor topic of a standard kind: its readings are converted to the kind's type."""
        return self.kind in SENSOR_KINDS

    @property
    def typed(self) -> bool:
        """A typed sensor's topic: its messages are written as CDR of their own type."""
        return self.kind == MESSAGE_KIND and self.msg_type is not None

    @property
    def report(self) -> bool:
        """A robot report or liveliness token: a DiagnosticArray."""
        return self.kind in REPORT_MESSAGES or self.kind == LIVELINESS

    @property
    def encoding(self) -> str:
        """``cdr`` (a standard ROS 2 type) or ``json`` (arpz's own, ``--include-internal``)."""
        if (
            self.sensor
            or self.typed
            or self.report
            or (self.kind == "command" and self.command_type)
        ):
            return CDR
        return JSON

    @property
    def type_name(self) -> str:
        """The channel's type: the ROS 2 type, or the arpz message of a JSON channel."""
        if self.typed:
            assert self.msg_type is not None
            return self.msg_type
        if self.sensor:
            return ros_type_for(self.kind)
        if self.report:
            return DIAGNOSTIC_ARRAY
        if self.kind == "command" and self.command_type:
            return self.command_type
        return _message_name(INTERNAL_MESSAGES[self.kind])

    @property
    def arpz_message(self) -> str:
        """The arpz message each of the channel's messages is, converted back."""
        if self.kind == LIVELINESS:
            return "bool"
        if self.typed:
            large = self.msg_type in LARGE_TYPES
            return _message_name(LargeSample if large else MessageSample)
        if self.sensor:
            return _message_name(LargeSample if self.kind in LARGE_KINDS else Sample)
        return _message_name({**REPORT_MESSAGES, **INTERNAL_MESSAGES}[self.kind])

    def schema(self) -> tuple[str, str, bytes] | None:
        """(name, encoding, data) of the channel's MCAP schema; None for a JSON channel, which
        is schemaless (MCAP allows it for ``json``): rosbags' reader knows the schema encodings
        ``ros2msg``, ``ros2idl`` and ``omgidl`` only and refuses a whole file holding a
        ``jsonschema`` one (``KeyError: 'jsonschema'``), where it lists a schemaless channel and
        reads the rest. The JSON Schema is in the channel's ``arpz_json_schema`` metadata."""
        if self.encoding == CDR:
            definition = self.definition or message_definition(self.type_name)
            return self.type_name, "ros2msg", definition.encode()
        return None

    def metadata(self) -> dict[str, str]:
        metadata = {
            "arpz_key": self.key,
            "arpz_kind": self.kind,
            "arpz_type": self.type_name,
            "arpz_message": self.arpz_message,
            "arpz_qos": msgspec.json.encode(self.qos).decode() if self.qos else "none",
            "offered_qos_profiles": offered_qos_yaml(self.qos),
        }
        if self.encoding == JSON:
            metadata["arpz_json_schema"] = json_schema(INTERNAL_MESSAGES[self.kind]).decode()
        return metadata


def json_schema(message_type: type[msgspec.Struct]) -> bytes:
    """The JSON Schema of an arpz message written as a JSON object of its fields (msgspec's
    schema, with an ``array_like`` struct's array turned into the object it is written as)."""
    schema = msgspec.json.schema(message_type)
    body = schema["$defs"][message_type.__name__]
    if body.get("type") == "array":
        names = message_type.__struct_fields__
        body = {key: value for key, value in body.items() if key in ("title", "description")} | {
            "type": "object",
            "properties": dict(zip(names, body["prefixItems"], strict=True)),
            "required": list(names[: body["minItems"]]),
        }
        schema["$defs"][message_type.__name__] = body
    return msgspec.json.encode(schema)


def internal_json(kind: str, message: msgspec.Struct) -> bytes:
    """An internal message (INTERNAL_MESSAGES) as the JSON object of its fields."""
    assert isinstance(message, INTERNAL_MESSAGES[kind]), (kind, message)
    return msgspec.json.encode(to_fields(message))


def liveliness_report(topic: Topic, alive: bool, stamp_ns: int) -> bytes:
    """A liveliness token appearing or vanishing, as a DiagnosticArray (STALE when it
    vanished)."""
    what = topic.name.split("/arpz/", 1)[-1]
    return serialize(
        report_to_ros(
            {"alive": alive},
            name=f"{topic.robot}/{what}",
            hardware_id=topic.robot,
            message=f"{what}: {'up' if alive else 'gone'}",
            stamp_ns=stamp_ns,
            level=OK if alive else STALE,
        )
    )


def recorded_message(topic: Topic, encoding: str, data: bytes) -> Any:
    """The arpz message (or a liveliness token's bool) of one recorded message of a
    non-sensor channel, in any form a recording holds: the DiagnosticArray of a report or token,
    the JSON of an internal message, or the msgpack of a recording made before issue 41.
    Raises ConversionError, msgspec's errors or ValueError on a message that is none of these."""
    kind = topic.kind
    if kind == LIVELINESS:
        if encoding == MSGPACK:
            return bool(msgspec.msgpack.decode(data))
        alive = report_from_cdr(data).fields.get("alive")
        if alive not in ("true", "false"):
            raise ConversionError(f"a liveliness report says alive={alive!r}")
        return alive == "true"
    message_type = {**REPORT_MESSAGES, **INTERNAL_MESSAGES}[kind]
    if encoding == MSGPACK:
        if kind == "sample":  # a camera's raw samples shared the kind with the scalar ones
            try:
                return msgspec.msgpack.decode(data, type=Sample)
            except DECODE_ERRORS:
                return msgspec.msgpack.decode(data, type=LargeSample)
        return msgspec.msgpack.decode(data, type=message_type)
    if encoding == JSON:
        return from_fields(message_type, msgspec.json.decode(data))
    return message_from_cdr(message_type, data)


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
        schema = self._schemas.get(topic.type_name, 0)
        definition = topic.schema()
        if not schema and definition is not None:
            schema = writer.register_schema(*definition)
            self._schemas[topic.type_name] = schema
        channel = writer.register_channel(topic.name, topic.encoding, schema, topic.metadata())
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
