"""``python -m arpz topic``: ``ros2 topic`` for an arpz fleet (docs/tools.md, "Topics").

    python -m arpz topic list  --connect tcp/10.0.0.1:7447 --fleet demo
    python -m arpz topic info  /robot1/lidar
    python -m arpz topic echo  /robot1/lidar [--json [FILE]] [--count N] [--reliable]
    python -m arpz topic hz    /robot1/lidar [--window N] [--duration S]
    python -m arpz topic bw    /robot1/camera
    python -m arpz topic delay /robot1/imu

The tool joins the fleet's router as a Zenoh client (scouting off), learns the fleet's graph from
what the fleet already publishes (``arpz.tools.fleet_graph``) and reads a topic the least
intrusive way (``arpz.tools.topic_stream``: a BEST_EFFORT channel reader unless ``--reliable``,
plain Zenoh where the fleet runs ``reliability = "none"``). Every exit path closes the session.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import sys
import threading
import time
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any, Final

import msgspec

from arpz import keys
from arpz.cli import (
    JSON_TO_STDOUT,
    add_fleet_client_options,
    add_json_option,
    connect_endpoints,
    emit_json,
    fail,
    stop_on_signals,
)
from arpz.config import RobotClockConfig
from arpz.errors import ArpzError
from arpz.messages import (
    ANNOUNCE_DECODER,
    CEDDP_STATS_DECODER,
    COMMAND_DECODER,
    DECODE_ERRORS,
    HELLO_DECODER,
    LARGE_SAMPLE_DECODER,
    QOS_ACK_DECODER,
    QOS_ASSIGNMENT_DECODER,
    SAMPLE_DECODER,
    STATS_DECODER,
    TELEMETRY_DECODER,
    LargeSample,
)
from arpz.protocol.qos import QosPolicyKind, incompatible_policy
from arpz.robot.clock_sync import ClockSync
from arpz.tools.fleet_graph import (
    CEDDP,
    Discovery,
    Endpoint,
    FleetGraph,
    TopicEntry,
    UnknownTopicError,
    clock_offset,
    discovering,
)
from arpz.tools.topic_stats import (
    DEFAULT_WINDOW,
    RateWindow,
    SizeWindow,
    ValueWindow,
    human_bytes,
)
from arpz.tools.topic_stream import Message, TopicStream, data_head, open_stream
from arpz.transport import SessionSettings, Transport
from arpz.zenoh_transport import ZenohTransport

TOOL: Final = "topic"
#: how long discovery watches the fleet at most before answering (less once every robot spoke)
DEFAULT_DISCOVERY_S: Final = 3.0

TOPIC_HELP: Final = (
    "the topic, as a ROS 2 name (/robot1/lidar, /robot1/cmd/velocity, /ceddp/stats), the same "
    "without the leading '/' (robot1/lidar), or an arpz key (arpz/FLEET/robot/robot1/sensor/lidar)"
)

#: arpz payload type -> its decoder (arpz/messages.py)
DECODERS: Final[dict[str, msgspec.msgpack.Decoder[Any]]] = {
    "Sample": SAMPLE_DECODER,
    "LargeSample": LARGE_SAMPLE_DECODER,
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
        line = json.dumps(document, sort_keys=True, default=str) + "\n"
        target = self._file if self._file is not None else sys.stdout
        target.write(line)
        target.flush()

    def close(self) -> None:
        if self._file is not None:
            self._file.close()


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


def list_lines(graph: FleetGraph) -> list[str]:
    """``topic list``'s text: the nodes, then one row per topic."""
    nodes = ", ".join(
        f"{n.name} ({n.mode or 'mode ?'}{'' if n.alive else ', gone'})" for n in graph.nodes
    )
    lines = [f"fleet {graph.fleet}: {nodes or 'no nodes'}"]
    rows = [("TOPIC", "TYPE", "ARPZ TYPE", "RATE Hz", "QOS", "WRITERS")]
    for t in graph.topics:
        rows.append(
            (
                t.name,
                t.ros_type or "-",
                arpz_type_text(t),
                rate_text(t),
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
    return lines


def matches(topic: TopicEntry) -> list[dict[str, object]]:
    """Every writer x reader pair of a topic with its verdict (arpz.protocol.qos matching); a
    plain publisher and a channel reader never match (the reader refuses its samples)."""
    out: list[dict[str, object]] = []
    for writer in topic.writers:
        for reader in topic.readers:
            policy: QosPolicyKind | None
            if writer.qos is None or reader.qos is None:
                policy = None if writer.qos is reader.qos else QosPolicyKind.RELIABILITY
            else:
                policy = incompatible_policy(writer.qos.as_profile(), reader.qos.as_profile())
            out.append(
                {
                    "writer": writer.guid or writer.node,
                    "reader": reader.guid or reader.node,
                    "compatible": policy is None,
                    "policy": policy.name if policy is not None else None,
                }
            )
    return out


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


def run_list(args: argparse.Namespace, ctx: Context) -> int:
    graph = ctx.graph
    if not graph.nodes and not graph.topics:
        others = (
            f"; this router carries fleets {', '.join(graph.other_fleets)}"
            if (graph.other_fleets)
            else ""
        )
        return fail(
            TOOL,
            f"nothing of fleet {graph.fleet!r} seen in {args.discovery_s:g} s at {args.connect} "
            f"(no CEDDP, no robot): check --connect and --fleet{others}",
            1,
        )
    emit_json(graph.as_dict(), args.json)
    text_out = sys.stderr if args.json == JSON_TO_STDOUT else sys.stdout
    print("\n".join(list_lines(graph)), file=text_out)
    return 0


def run_info(args: argparse.Namespace, ctx: Context) -> int:
    topic = ctx.graph.topic(args.topic)
    emit_json({**topic.as_dict(), "matches": matches(topic)}, args.json)
    text_out = sys.stderr if args.json == JSON_TO_STDOUT else sys.stdout
    print("\n".join(info_lines(topic)), file=text_out)
    return 0


# ----------------------------------------------------------------------------- echo


def decode(topic: TopicEntry, payload: bytes) -> object:
    """The arpz message of ``payload``; raises one of DECODE_ERRORS on bad bytes."""
    decoder = DECODERS.get(topic.arpz_type)
    if decoder is None:
        return {"bytes": len(payload)}
    return decoder.decode(payload)


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


class Echo:
    """``topic echo``: every message decoded, as text or one JSON object per line."""

    def __init__(self, topic: TopicEntry, out: Output, count: int) -> None:
        self.topic = topic
        self.out = out
        self.count = count
        self.printed = 0
        self.decode_errors = 0

    def on_message(self, message: Message) -> None:
        try:
            decoded = decode(self.topic, message.payload)
        except DECODE_ERRORS as exc:
            self.decode_errors += 1
            if self.decode_errors in (1, 10, 100) or self.decode_errors % 1000 == 0:
                self.out.text(f"undecodable message #{self.decode_errors} on {message.key}: {exc}")
            return
        document = message_document(self.topic, message, decoded)
        self.out.record(document)
        if self.out.text_wanted:  # with --json on stdout the JSON lines are the messages
            self.out.text(echo_text(self.topic, document))
        self.printed += 1

    @property
    def done(self) -> bool:
        return 0 < self.count <= self.printed

    def report(self, stream: TopicStream) -> None:
        """Echo prints messages, not periodic reports."""

    def final(self, stream: TopicStream) -> None:
        counters = {**stream.counters(), "decode_errors": self.decode_errors}
        self.out.record(
            {
                "final": True,
                "topic": self.topic.name,
                "messages": self.printed,
                "reader": stream.description,
                "counters": counters,
            }
        )
        self.out.text(
            f"{self.printed} messages on {self.topic.name} ({stream.description}); "
            + counters_text(counters)
        )


def counters_text(counters: dict[str, int]) -> str:
    return "counters: " + ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in counters.items())


# ----------------------------------------------------------------------------- hz, bw, delay


class Periodic:
    """The shared loop of hz, bw and delay: figures every second, a final figure at the end."""

    what = ""

    def __init__(self, topic: TopicEntry, out: Output) -> None:
        self.topic = topic
        self.out = out
        self.start_s = time.monotonic()
        self._seen_at_report = 0
        self.messages = 0

    done = False

    def on_message(self, message: Message) -> None:
        self.messages += 1
        self.add(message)

    def add(self, message: Message) -> None:
        raise NotImplementedError

    def figures(self, now_s: float) -> dict[str, object] | None:
        raise NotImplementedError

    def figure_lines(self, figures: dict[str, object]) -> list[str]:
        raise NotImplementedError

    def report(self, stream: TopicStream) -> None:
        now = time.monotonic()
        counters = stream.counters()
        if self.messages == self._seen_at_report:
            self.out.text("no new messages")
            self.out.record(
                {
                    "t_s": round(now - self.start_s, 3),
                    "messages": self.messages,
                    "new": 0,
                    "counters": counters,
                }
            )
            return
        self._seen_at_report = self.messages
        figures = self.figures(now)
        if figures is None:
            return
        self.out.record(
            {
                "t_s": round(now - self.start_s, 3),
                "messages": self.messages,
                **figures,
                "counters": counters,
            }
        )
        for line in self.figure_lines(figures):
            self.out.text(line)
        self.out.text("\t" + counters_text(_short(counters)))

    def final(self, stream: TopicStream) -> None:
        now = time.monotonic()
        counters = stream.counters()
        figures = self.figures(now) or {}
        self.out.record(
            {
                "final": True,
                "topic": self.topic.name,
                "messages": self.messages,
                "duration_s": round(now - self.start_s, 3),
                "reader": stream.description,
                **figures,
                "counters": counters,
            }
        )
        self.out.text(
            f"{self.messages} messages on {self.topic.name} in {now - self.start_s:.1f} s "
            f"({stream.description}); {counters_text(counters)}"
        )


def _short(counters: dict[str, int]) -> dict[str, int]:
    return {k: counters[k] for k in ("lost", "retransmitted", "matched_writers") if k in counters}


def _spread_dict(spread: Any, prefix: str) -> dict[str, object]:
    return {
        f"{prefix}mean_s": spread.mean,
        f"{prefix}min_s": spread.min,
        f"{prefix}max_s": spread.max,
        f"{prefix}std_s": spread.std,
    }


class Hz(Periodic):
    def __init__(self, topic: TopicEntry, out: Output, window: int) -> None:
        super().__init__(topic, out)
        self.window = RateWindow(window)

    def add(self, message: Message) -> None:
        self.window.add(message.arrival_s)

    def figures(self, now_s: float) -> dict[str, object] | None:
        periods = self.window.periods()
        rate = self.window.rate_hz()
        if periods is None or rate is None:
            return None
        return {"rate_hz": rate, **_spread_dict(periods, "period_"), "window": periods.n + 1}

    def figure_lines(self, f: dict[str, object]) -> list[str]:
        return [
            f"average rate: {f['rate_hz']:.3f}",
            f"\tmin: {f['period_min_s']:.3f}s max: {f['period_max_s']:.3f}s "
            f"std dev: {f['period_std_s']:.5f}s window: {f['window']}",
        ]


class Bw(Periodic):
    def __init__(self, topic: TopicEntry, out: Output, window: int) -> None:
        super().__init__(topic, out)
        self.window = SizeWindow(window)

    def add(self, message: Message) -> None:
        self.window.add(message.arrival_s, len(message.payload))

    def figures(self, now_s: float) -> dict[str, object] | None:
        sizes = self.window.sizes()
        rate = self.window.bytes_per_s()
        if sizes is None or rate is None:
            return None
        return {
            "bytes_per_s": rate,
            "size_mean": sizes.mean,
            "size_min": sizes.min,
            "size_max": sizes.max,
            "window": sizes.n,
            "total_bytes": self.window.total_bytes,
        }

    def figure_lines(self, f: dict[str, object]) -> list[str]:
        return [
            f"{human_bytes(float(f['bytes_per_s']))}/s from {f['window']} messages",  # type: ignore[arg-type]
            f"\tMessage size mean: {human_bytes(float(f['size_mean']))} "  # type: ignore[arg-type]
            f"min: {human_bytes(float(f['size_min']))} "  # type: ignore[arg-type]
            f"max: {human_bytes(float(f['size_max']))}",  # type: ignore[arg-type]
        ]


#: (correction_ns or None when unknown, a sentence saying where it comes from)
Correction = tuple[int | None, str]


class Delay(Periodic):
    """Arrival (this host's wall clock) minus the source stamp, corrected by the clocks' offsets
    when they are known (``clock_correction``)."""

    def __init__(
        self,
        topic: TopicEntry,
        out: Output,
        window: int,
        correction: Callable[[], Correction],
    ) -> None:
        super().__init__(topic, out)
        self.window = ValueWindow(window)
        self._correction = correction
        self.correction_ns, self.clock_note = correction()
        self.unstamped = 0

    def add(self, message: Message) -> None:
        head = data_head(message.payload)
        stamp_ns = head[2] if head is not None else message.stamp_ns
        if stamp_ns is None:
            self.unstamped += 1
            return
        self.window.add((message.arrival_ns - stamp_ns - (self.correction_ns or 0)) / 1e9)

    def report(self, stream: TopicStream) -> None:
        self.correction_ns, self.clock_note = self._correction()
        super().report(stream)

    def figures(self, now_s: float) -> dict[str, object] | None:
        spread = self.window.spread()
        if spread is None:
            return None
        return {
            "delay_mean_s": spread.mean,
            "delay_min_s": spread.min,
            "delay_max_s": spread.max,
            "delay_std_s": spread.std,
            "window": spread.n,
            "correction_s": None if self.correction_ns is None else self.correction_ns / 1e9,
            "corrected": self.correction_ns is not None,
            "clock": self.clock_note,
            "unstamped": self.unstamped,
        }

    def figure_lines(self, f: dict[str, object]) -> list[str]:
        return [
            f"average delay: {f['delay_mean_s']:.6f}",
            f"\tmin: {f['delay_min_s']:.6f}s max: {f['delay_max_s']:.6f}s "
            f"std dev: {f['delay_std_s']:.6f}s window: {f['window']}",
            f"\t{self.clock_note}",
        ]


class HostClock:
    """This host's clock against the CEDDP's, measured as a robot measures its own (NTP-style
    exchanges on ``ceddp/clock``, the fastest of the last few: arpz.robot.clock_sync), so that a
    delay is corrected on any host, not only on the CEDDP's."""

    def __init__(self, transport: Transport, fleet: str) -> None:
        self._sync = ClockSync(RobotClockConfig(), transport, fleet)
        self._sync.first_estimate(1.0)

    def refresh(self) -> None:
        self._sync.exchange()

    def offset_ns(self) -> int | None:
        """The CEDDP's clock minus this host's, None before (or without) an answer."""
        return self._sync.stats().offset_ns


def _ms(ns: int) -> str:
    return f"{ns / 1e6:+.3f} ms"


def clock_correction(
    discovery: Discovery, topic: TopicEntry, host: HostClock | None
) -> Callable[[], Correction]:
    """What ``topic delay`` subtracts from arrival - stamp: the writer's offset to the CEDDP's
    clock (the owner robot's latest ``RobotStats.clock``; 0 for the CEDDP's own keys) minus this
    host's (measured by ``HostClock``; taken as 0 when the CEDDP does not answer). A writer
    whose offset is unknown is not corrected, and the note says so."""

    def correction() -> Correction:
        if host is not None:
            host.refresh()
        host_ns = host.offset_ns() if host is not None else None
        host_text = (
            f"this host {_ms(host_ns)}"
            if host_ns is not None
            else "this host not measured (no answer on ceddp/clock), taken as 0"
        )
        if topic.owner == CEDDP:
            writer_ns = 0
            writer_text = "writer: the CEDDP (the reference)"
        else:
            offset = clock_offset(discovery.graph().stats.get(topic.owner))
            if offset is None:
                return None, f"clock offset of {topic.owner}: offset unknown, uncorrected"
            writer_ns = offset.offset_ns
            writer_text = f"{topic.owner} {_ms(writer_ns)}"
        return (
            writer_ns - (host_ns or 0),
            f"clock offsets to the CEDDP: {writer_text}, {host_text}; corrected",
        )

    return correction


# ----------------------------------------------------------------------------- the stream loop


class Context:
    """What every subcommand gets: the session, the fleet's graph, discovery (kept open) and
    the stop event (SIGINT/SIGTERM)."""

    def __init__(
        self,
        transport: Transport,
        discovery: Discovery,
        graph: FleetGraph,
        stop: threading.Event,
    ) -> None:
        self.transport = transport
        self.discovery = discovery
        self.graph = graph
        self.stop = stop


Handler = Echo | Hz | Bw | Delay


def stream_loop(
    args: argparse.Namespace, ctx: Context, make: Callable[[TopicEntry, Output], Handler]
) -> int:
    """Open the topic's reader and feed its messages to ``make``'s handler until ``--duration``,
    ``--count`` or a signal; figures every second, the counters at the end."""
    topic = ctx.graph.topic(args.topic)
    if args.reliable and any(w.qos is not None and not w.qos.reliable for w in topic.writers):
        return fail(
            TOOL,
            f"{topic.name} has a BEST_EFFORT writer, which a RELIABLE reader cannot match: "
            "drop --reliable",
        )
    out = Output(args.json)
    try:
        with open_stream(ctx.transport, topic, reliable=args.reliable) as stream:
            handler = make(topic, out)
            print(
                f"reading {topic.name} ({topic.key}) with a {stream.description}",
                file=sys.stderr,
                flush=True,
            )
            deadline = time.monotonic() + args.duration if args.duration else float("inf")
            next_report = time.monotonic() + 1.0
            while not ctx.stop.is_set() and not handler.done:
                now = time.monotonic()
                if now >= deadline:
                    break
                message = stream.get(min(next_report, deadline, now + 0.2) - now)
                if message is not None:
                    handler.on_message(message)
                if time.monotonic() >= next_report:
                    handler.report(stream)
                    next_report += 1.0
            # stop reading, then take what was already delivered: the final counters and the
            # messages shown agree exactly
            stream.close()
            while not handler.done and (message := stream.get(0.0)) is not None:
                handler.on_message(message)
            handler.final(stream)
    finally:
        out.close()
    return 0


def run_echo(args: argparse.Namespace, ctx: Context) -> int:
    return stream_loop(args, ctx, lambda topic, out: Echo(topic, out, args.count))


def run_hz(args: argparse.Namespace, ctx: Context) -> int:
    return stream_loop(args, ctx, lambda topic, out: Hz(topic, out, args.window))


def run_bw(args: argparse.Namespace, ctx: Context) -> int:
    return stream_loop(args, ctx, lambda topic, out: Bw(topic, out, args.window))


def run_delay(args: argparse.Namespace, ctx: Context) -> int:
    return stream_loop(
        args,
        ctx,
        lambda topic, out: Delay(
            topic,
            out,
            args.window,
            clock_correction(ctx.discovery, topic, HostClock(ctx.transport, args.fleet)),
        ),
    )


COMMANDS: Final[dict[str, Callable[[argparse.Namespace, Context], int]]] = {
    "list": run_list,
    "info": run_info,
    "echo": run_echo,
    "hz": run_hz,
    "bw": run_bw,
    "delay": run_delay,
}


# ----------------------------------------------------------------------------- the parser


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="arpz topic",
        description="Inspect a running fleet's topics, as `ros2 topic` does: list, info, echo, "
        "hz, bw, delay. The tool joins the fleet's router as a client.",
        epilog="TOPIC forms: " + TOPIC_HELP + ". See docs/tools.md.",
    )
    with contextlib.suppress(ImportError):  # --version where arpz.cli offers it
        from arpz.cli import add_version_option  # type: ignore[attr-defined,unused-ignore]

        add_version_option(parser)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    helps = {
        "list": "every topic with its type, rate, QoS and writers",
        "info": "QoS of each writer and reader of TOPIC, matched or incompatible",
        "echo": "print TOPIC's messages, decoded",
        "hz": "TOPIC's rate, with min/max/std dev of the period over a window",
        "bw": "TOPIC's bandwidth and message sizes over a window",
        "delay": "TOPIC's delay from source stamp to arrival, clock offset corrected when known",
    }
    for name, text in helps.items():
        p = sub.add_parser(name, help=text, description=text[0].upper() + text[1:] + ".")
        add_fleet_client_options(p)
        add_json_option(
            p,
            "one JSON object per line (messages or figures, then a final summary)"
            if name not in ("list", "info")
            else "the result",
        )
        p.add_argument(
            "--discovery-s",
            type=float,
            default=DEFAULT_DISCOVERY_S,
            metavar="S",
            help="watch the fleet at most this long to learn its topics (default %(default)s)",
        )
        if name == "list":
            continue
        p.add_argument("topic", metavar="TOPIC", help=TOPIC_HELP)
        if name == "info":
            continue
        p.add_argument(
            "--duration",
            type=float,
            default=0.0,
            metavar="S",
            help="stop after S seconds (default: until Ctrl-C)",
        )
        p.add_argument(
            "--reliable",
            action="store_true",
            help="read as a RELIABLE reader (NACKs make the writers resend what this tool "
            "missed; KEEP_ALL writers then wait for it); default BEST_EFFORT, which asks "
            "nothing of the writers",
        )
        if name == "echo":
            p.add_argument(
                "--count",
                type=int,
                default=0,
                metavar="N",
                help="stop after N messages (default: no limit)",
            )
        else:
            p.add_argument(
                "--window",
                type=int,
                default=DEFAULT_WINDOW,
                metavar="N",
                help="messages in the statistics window (default %(default)s)",
            )
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        endpoints = connect_endpoints(args.connect)
        keys.check_chunk(args.fleet, what="--fleet")
        if getattr(args, "duration", 0.0) < 0 or args.discovery_s <= 0:
            raise ArpzError("--duration must be >= 0 and --discovery-s > 0 (seconds)")
        if getattr(args, "window", DEFAULT_WINDOW) < 2 or getattr(args, "count", 0) < 0:
            raise ArpzError("--window must be >= 2 and --count >= 0")
    except ArpzError as exc:
        return fail(TOOL, str(exc))
    stop = stop_on_signals()
    settings = SessionSettings(mode="client", connect=endpoints, config_file=args.zenoh_config)
    try:
        transport = ZenohTransport.open(settings, timeout_s=2.0)
    except ArpzError as exc:
        return fail(TOOL, str(exc), 1)
    try:
        with discovering(transport, args.fleet) as discovery:
            graph = discovery.settle(max_s=args.discovery_s)
            return COMMANDS[args.command](args, Context(transport, discovery, graph, stop))
    except UnknownTopicError as exc:
        return fail(TOOL, str(exc), 2)
    except ArpzError as exc:
        return fail(TOOL, str(exc), 1)
    except BrokenPipeError:  # `arpz topic echo ... | head`
        return 0
    finally:
        transport.close()


if __name__ == "__main__":
    sys.exit(main())
