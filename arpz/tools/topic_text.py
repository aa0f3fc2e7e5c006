"""What ``arpz topic`` prints: the list and info text, decoded messages as one line, a block or
JSON, and the counters; ``Output`` puts words and JSON where ``--json`` says (docs/tools.md,
"Conventions": with ``--json`` on stdout the words go to stderr)."""

from __future__ import annotations

import base64
import datetime
import json
import sys
import zlib
from pathlib import Path
from typing import IO, Any, Final

import msgspec

from arpz.core import keys
from arpz.core.messages import (
    ANNOUNCE_DECODER,
    CEDDP_STATS_DECODER,
    COMMAND_DECODER,
    HELLO_DECODER,
    LARGE_SAMPLE_DECODER,
    MESSAGE_SAMPLE_DECODER,
    QOS_ACK_DECODER,
    QOS_ASSIGNMENT_DECODER,
    SAMPLE_DECODER,
    STATS_DECODER,
    TELEMETRY_DECODER,
    LargeSample,
    MessageSample,
)
from arpz.core.msgtypes import MessageTypes, as_dict
from arpz.runtime.startup import JSON_TO_STDOUT
from arpz.tools.fleet_graph import (
    Endpoint,
    FleetGraph,
    TopicEntry,
    matches,
)
from arpz.tools.topic_stream import Message

DECODERS: Final[dict[str, msgspec.msgpack.Decoder[Any]]] = {
    "Sample": SAMPLE_DECODER,
    "LargeSample": LARGE_SAMPLE_DECODER,
    "MessageSample": MESSAGE_SAMPLE_DECODER,
    "Hello": HELLO_DECODER,
    "Command": COMMAND_DECODER,
    "RobotStats": STATS_DECODER,
    "Announce": ANNOUNCE_DECODER,
    "QosAck": QOS_ACK_DECODER,
    "Telemetry": TELEMETRY_DECODER,
    "CeddpStats": CEDDP_STATS_DECODER,
    "QosAssignmentMsg": QOS_ASSIGNMENT_DECODER,
}
#: messages printed on one line each; the others (reports) as an indented block
ONE_LINE_TYPES: Final = frozenset({"Sample", "LargeSample", "Hello", "Command", "Telemetry"})


# ----------------------------------------------------------------------------- output


class Output:
    """Text for people on stdout, and with ``--json``: JSON (one object per line for the
    streaming commands) on stdout instead of the text, or into FILE beside it."""

    def __init__(self, json_target: str | None) -> None:
        self.json_target = json_target
        self._file: IO[str] | None = None
        if json_target not in (None, JSON_TO_STDOUT):
            self._file = Path(json_target).open("w", encoding="utf-8")  # noqa: SIM115

    @property
    def text_wanted(self) -> bool:
        return self.json_target != JSON_TO_STDOUT

    def text(self, line: str) -> None:
        """Words for people: on stdout, or on stderr while stdout carries the JSON."""
        print(line, file=sys.stdout if self.text_wanted else sys.stderr, flush=True)

    def record(self, document: object) -> None:
        if self.json_target is None:
            return
        line = json.dumps(document, sort_keys=True, default=_json_value) + "\n"
        target = self._file if self._file is not None else sys.stdout
        target.write(line)
        target.flush()

    def close(self) -> None:
        if self._file is not None:
            self._file.close()


def _json_value(value: object) -> object:
    """bytes (a typed message's ``uint8[]``) as base64, as msgspec writes them; else str."""
    if isinstance(value, bytes | bytearray | memoryview):
        return base64.b64encode(bytes(value)).decode()
    return str(value)


# ----------------------------------------------------------------------------- list, info


def rate_text(topic: TopicEntry) -> str:
    measured = f"{topic.measured_rate_hz:.1f}" if topic.measured_rate_hz is not None else "-"
    if topic.announced_rate_hz is None:
        return measured
    return f"{measured}/{topic.announced_rate_hz:g}"


def arpz_type_text(topic: TopicEntry) -> str:
    if topic.value_type and topic.arpz_type in ("Sample", "LargeSample"):
        return f"{topic.arpz_type}[{topic.value_type}]"
    if topic.arpz_type == "LargeSample":
        return "LargeSample[bytes]"
    return topic.arpz_type


def writers_text(writers: tuple[Endpoint, ...]) -> str:
    counts: dict[str, int] = {}
    for writer in writers:
        counts[writer.node] = counts.get(writer.node, 0) + 1
    return ", ".join(f"{n} x{c}" if c > 1 else n for n, c in counts.items()) or "-"


def qos_text(endpoints: tuple[Endpoint, ...]) -> str:
    return "; ".join(dict.fromkeys(e.describe_qos() for e in endpoints)) or "-"


def health_text(graph: FleetGraph, topic: TopicEntry) -> str:
    """A sensor topic's health from its robot's last report: "ok", "NO READING" (none for the
    robot's last report interval), driver errors and late reads since the robot started; "-"
    for other topics and sensors not reported yet."""
    parsed = keys.parse_robot_key(topic.key)
    if parsed is None or parsed[1] not in ("sensor", "frames") or parsed[2] == keys.HELLO:
        return "-"
    robot, _, name = parsed
    stats = graph.stats.get(robot)
    counters = stats.topics.get(name) if stats is not None else None
    if stats is None or counters is None:
        return "-"
    said = []
    if name in stats.silent_sensors:
        said.append("NO READING")
    if counters.driver_errors:
        said.append(f"{counters.driver_errors} driver errors")
    if counters.late_reads:
        said.append(f"{counters.late_reads} late reads")
    return ", ".join(said) or "ok"


def list_lines(graph: FleetGraph) -> list[str]:
    """``topic list``'s text: the nodes, then one row per topic."""
    nodes = ", ".join(
        f"{n.name} ({n.mode or 'mode ?'}{'' if n.alive else ', gone'})" for n in graph.nodes
    )
    lines = [f"fleet {graph.fleet}: {nodes or 'no nodes'}"]
    rows = [("TOPIC", "TYPE", "ARPZ TYPE", "RATE Hz", "HEALTH", "QOS", "WRITERS")]
    for t in graph.topics:
        rows.append(
            (
                t.name,
                t.ros_type or "-",
                arpz_type_text(t),
                rate_text(t),
                health_text(graph, t),
                qos_text(t.writers),
                writers_text(t.writers),
            )
        )
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]) - 1)]
    for row in rows:
        cells = [cell.ljust(width) for cell, width in zip(row, widths, strict=False)]
        lines.append("  ".join([*cells, row[-1]]).rstrip())
    lines.append(
        "RATE: measured by the writer over its last report / announced (configured or assigned)"
    )
    lines.append(
        "HEALTH: a sensor's driver errors (reads that gave no reading) and late reads since its "
        "robot started; NO READING: none for the robot's last report interval"
    )
    if graph.ros2:
        lines.append("ROS 2 (rmw_zenoh) on the same router:")
        ros_rows = [("TOPIC", "TYPE", "ROLE", "NODE", "QOS")]
        ros_rows += [(r.topic, r.ros_type, r.role, r.node, r.qos.describe()) for r in graph.ros2]
        ros_widths = [max(len(ros_row[i]) for ros_row in ros_rows) for i in range(4)]
        for ros_row in ros_rows:
            padded = [c.ljust(w) for c, w in zip(ros_row, ros_widths, strict=False)]
            lines.append("  " + "  ".join([*padded, ros_row[-1]]).rstrip())
    return lines


def info_lines(topic: TopicEntry) -> list[str]:
    types = ", ".join(topic.ros_types) or "(no ROS 2 type)"
    value = f", value {topic.value_type}" if topic.value_type else ""
    kind = f", kind {topic.kind}" if topic.kind else ""
    lines = [
        f"Topic: {topic.name}",
        f"Key: {topic.key}",
        f"Type: {types} (arpz {topic.arpz_type}{value}{kind})",
        f"Mode: {topic.mode or 'unknown'}"
        + ("  (reliable channel)" if topic.reliable_channel else "  (plain Zenoh puts)"),
        f"Rate: measured {_hz(topic.measured_rate_hz)}, announced {_hz(topic.announced_rate_hz)}",
    ]
    if topic.assigned_depth is not None:
        lines.append(f"History: KEEP_LAST {topic.assigned_depth} (the CEDDP's QoS assignment)")
    lines.append("")
    for title, endpoints in (("Publisher", topic.writers), ("Subscription", topic.readers)):
        lines.append(f"{title} count: {len(endpoints)}")
        for e in endpoints:
            guid = f"  guid {e.guid}" if e.guid else ""
            lines.append(f"  node {e.node}{guid}  QoS: {e.describe_qos()}")
    pairs = matches(topic)
    if pairs:
        lines.append("")
        lines.append("Matching (writer -> reader):")
        for pair in pairs:
            verdict = "matched" if pair["compatible"] else f"INCOMPATIBLE ({pair['policy']})"
            lines.append(f"  {pair['writer']} -> {pair['reader']}: {verdict}")
    lines.append("")
    if not topic.reliable_channel:
        lines.append("Plain Zenoh subscribers declare no token: this topic's readers are unseen.")
    lines.append(
        "QoS shown is what each endpoint's liveliness token carries (reliability, durability, "
        "deadline, liveliness, lease); history and depth are not advertised."
    )
    return lines


def _hz(value: float | None) -> str:
    return f"{value:.2f} Hz" if value is not None else "-"


# ----------------------------------------------------------------------------- echo


def decode(topic: TopicEntry, payload: bytes) -> object:
    """The arpz message of ``payload``; raises one of DECODE_ERRORS on bad bytes. A typed
    topic's sample comes back with its message as a dict of fields (``TypedSample``)."""
    decoder = DECODERS.get(topic.arpz_type)
    if decoder is None:
        return {"bytes": len(payload)}
    decoded = decoder.decode(payload)
    if topic.msg_type is None or not isinstance(decoded, MessageSample | LargeSample):
        return decoded
    return typed_sample(topic.msg_type, decoded)


class TypedSample(msgspec.Struct, frozen=True):
    """A typed topic's sample as ``echo`` shows it: the message's fields by name."""

    writer: str
    seq: int
    stamp_ns: int
    type: str
    message: dict[str, object]


_TYPES: list[MessageTypes] = []


def use_msg_paths(paths: list[str]) -> None:
    """Decode typed topics with these ``.msg`` folders too (``topic echo --msg-path``)."""
    types = MessageTypes()
    types.add_msg_paths(paths)
    _TYPES[:] = [types]


def typed_sample(msg_type: str, sample: MessageSample | LargeSample) -> object:
    """``sample`` with its message decoded by the standard ROS 2 types; a type this tool does
    not know (a team's own) shows as its size and type."""
    if not _TYPES:
        _TYPES.append(MessageTypes())
    types = _TYPES[0]
    if not types.known(msg_type):
        return {
            "type": msg_type,
            "bytes": len(bytes(sample.value)),
            "decoded": "no: a type of the fleet's own; give its folder with --msg-path",
        }
    message = types.decode(msg_type, sample.value)
    return TypedSample(sample.writer, sample.seq, sample.stamp_ns, msg_type, as_dict(message))


#: in text, a longer array is shown as its first items and its length (``ros2 topic echo``
#: truncates at 128 too), and bytes (an image's pixels) as their length and CRC; ``--json``
#: carries them whole
SHOWN_ITEMS: Final = 128


def _shorten(value: object) -> object:
    if isinstance(value, dict):
        return {key: _shorten(item) for key, item in value.items()}
    if isinstance(value, bytes | bytearray | memoryview):
        data = bytes(value)
        if len(data) <= 32:
            return list(data)
        return {"bytes": len(data), "crc32": f"{zlib.crc32(data):08x}"}
    if isinstance(value, list):
        if len(value) <= SHOWN_ITEMS:
            return [_shorten(item) for item in value]
        return [_shorten(item) for item in value[:SHOWN_ITEMS]] + [f"... {len(value)} items"]
    return value


def large_summary(kind: str | None, value: bytes) -> dict[str, object]:
    """What a camera frame or point cloud is, instead of its megabyte: size, what it holds
    (docs/sensors.md layouts: RGB bytes, float32 x, y, z points) and a CRC to tell frames apart."""
    summary: dict[str, object] = {"bytes": len(value), "crc32": f"{zlib.crc32(value):08x}"}
    if kind == "camera":
        summary["pixels"] = len(value) // 3
    elif kind == "pointcloud":
        summary["points"] = len(value) // 12
    return summary


def named_fields(message: msgspec.Struct) -> object:
    """A message as builtins, array-like ones with their fields named."""
    built = msgspec.to_builtins(message)
    if isinstance(built, list):
        return dict(zip(message.__struct_fields__, built, strict=False))
    return built


def message_document(topic: TopicEntry, message: Message, decoded: object) -> dict[str, object]:
    """One ``echo --json`` line: the decoded message with its topic, key and arrival time."""
    body: object
    if isinstance(decoded, LargeSample):
        body = named_fields(msgspec.structs.replace(decoded, value=b""))
        assert isinstance(body, dict)
        body["value"] = large_summary(topic.kind, decoded.value)
    elif isinstance(decoded, TypedSample):  # bytes kept: text shortens them, JSON base64
        body = {field: getattr(decoded, field) for field in decoded.__struct_fields__}
    elif isinstance(decoded, msgspec.Struct):
        body = named_fields(decoded)
    else:
        body = decoded
    document: dict[str, object] = {
        "topic": topic.name,
        "key": message.key,
        "arrival_ns": message.arrival_ns,
        "message": body,
    }
    if message.frame is not None:
        document["frame"] = {"id": message.frame.frame_id, "fragments": message.frame.fragments}
    if message.retransmitted:
        document["retransmitted"] = True
    return document


def stamp_text(stamp_ns: int) -> str:
    moment = datetime.datetime.fromtimestamp(stamp_ns / 1e9, tz=datetime.UTC)
    return moment.isoformat(timespec="microseconds").replace("+00:00", "Z")


def echo_text(topic: TopicEntry, document: dict[str, object]) -> str:
    body = document["message"]
    if topic.arpz_type in ONE_LINE_TYPES and isinstance(body, dict):
        parts = []
        for name, value in body.items():
            if name in ("stamp_ns", "changed_ns", "since_ns", "t0_ns") and isinstance(value, int):
                parts.append(f"{name.removesuffix('_ns')}={stamp_text(value) if value else 0}")
            elif isinstance(value, dict):
                parts.append(f"{name}=" + ",".join(f"{k}:{v}" for k, v in value.items()))
            else:
                parts.append(f"{name}={value}")
        frame = document.get("frame")
        if isinstance(frame, dict):
            parts.append(f"frame={frame['id']} fragments={frame['fragments']}")
        return "  ".join(parts)
    if topic.msg_type is not None:
        body = _shorten(body)
    return yaml_text(body) + "\n---"


def yaml_text(value: object, indent: int = 0) -> str:
    """A nested value as indented ``key: value`` lines (what ``ros2 topic echo`` prints)."""
    pad = "  " * indent
    if isinstance(value, dict):
        if not value:
            return f"{pad}{{}}"
        lines = []
        for k, v in value.items():
            if isinstance(v, dict | list) and v:
                lines.append(f"{pad}{k}:")
                lines.append(yaml_text(v, indent + 1))
            else:
                shown = json.dumps(v) if isinstance(v, str | bool | None) else v
                lines.append(f"{pad}{k}: {shown}")
        return "\n".join(lines)
    if isinstance(value, list):
        if not value:
            return f"{pad}[]"
        if all(not isinstance(v, dict | list) for v in value):
            return f"{pad}{value}"
        return "\n".join(f"{pad}-\n{yaml_text(v, indent + 1)}" for v in value)
    return f"{pad}{value}"


def counters_text(counters: dict[str, int]) -> str:
    return "counters: " + ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in counters.items())
