"""``arpz record``: a running fleet into MCAP files that ROS 2 tools and Foxglove open.

``Recorder`` joins the fleet as one more reader of every robot's sensor topics, frames, reports
and commands, through the reliable channel when the fleet runs it (the CEDDP's mode token says
so) and as a plain subscriber otherwise, so what it could not get is counted by the channel and
said in the summary, never lost silently. Under access control (the CEDDP says so in its stats)
it reads without writing anything, as an observer's certificate requires: BEST_EFFORT channel
readers, which send no ACKNACK (losses are still counted from the writers' sequence numbers).
It learns each topic's kind from the robots' announcements and writes each key as one MCAP
channel of a standard ROS 2 type (arpz.tools._recording gives the layout); arpz's own messages
that have none are left out unless ``--include-internal``. The channel callbacks only queue; one
thread (``run``) converts and writes.

Usage: ``python -m arpz record --out fleet.mcap [--duration S] [TOPIC_PATTERN ...]``
(docs/tools.md "Recording and replay").
"""

from __future__ import annotations

import argparse
import logging
import queue
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec

from arpz.channel import (
    DataInfo,
    FrameInfo,
    FrameReader,
    MessageLostStatus,
    Reader,
    ReaderEventCallbacks,
)
from arpz.core import keys
from arpz.core.config import (
    LARGE_KINDS,
    LARGE_SAMPLE_BYTES,
    LARGE_TYPES,
    MESSAGE_KIND,
    SENSOR_KINDS,
    CeddpConfig,
    ConfigError,
    RobotConfig,
    TrafficQos,
    load_toml,
)
from arpz.core.errors import ArpzError
from arpz.core.messages import (
    COMMAND_DECODER,
    DECODE_ERRORS,
    LARGE_SAMPLE_DECODER,
    MESSAGE_SAMPLE_DECODER,
    SAMPLE_DECODER,
    Announce,
    Command,
    Hello,
    LargeSample,
    QosAck,
    RobotStats,
    Sample,
    Telemetry,
)
from arpz.core.msgtypes import MessageTypes
from arpz.core.protocol.qos import DurabilityPolicy, QosProfile, ReliabilityPolicy
from arpz.core.rosmsg.commands import command_cdr, command_type
from arpz.core.rosmsg.convert import ConversionError, is_exact, to_cdr
from arpz.core.rosmsg.reports import OK, WARN, report_cdr
from arpz.core.throttled_log import ThrottledLog
from arpz.core.transport import Handle, Transport, TransportError
from arpz.core.version import arpz_version
from arpz.runtime import startup
from arpz.tools._recording import (
    INTERNAL_MESSAGES,
    LIVELINESS,
    REPORT_MESSAGES,
    McapSink,
    Topic,
    internal_json,
    liveliness_report,
    matches,
    open_client,
    report_kind,
)
from arpz.tools.fleet_graph import CeddpStatsWatch

log = logging.getLogger(__name__)
throttled = ThrottledLog(log)

#: how long a sensor sample waits for the announcement that names its topic's kind before it is
#: recorded as a raw arpz Sample
_UNANNOUNCED_WAIT_S = 3.0
#: how long the recorder waits for the CEDDP's mode token before it decides the mode
_MODE_WAIT_S = 2.0
#: how long it then waits for the CEDDP's stats (every metrics_period_s, 0.5 s by default) to
#: learn whether access control is in force
_STATS_WAIT_S = 3.0
#: samples waiting for the writing thread; beyond, the channel's readers wait (backpressure:
#: the channel recovers or counts what it then cannot deliver)
_QUEUE_LIMIT = 100_000

SENSOR, FRAME, COMMAND, REPORT = "sensor", "frame", "command", "report"


@dataclass
class TopicTally:
    """What the recording got on one key."""

    topic: Topic
    messages: int = 0
    bytes: int = 0
    #: irrecoverably lost during the recording (the channel's MESSAGE_LOST, or seq gaps plain)
    lost: int = 0
    #: float32 readings with more digits than float32 keeps (rounded in the ROS 2 message)
    rounded: int = 0
    #: payloads that could not be decoded or converted: counted, not written
    undecodable: int = 0


@dataclass(frozen=True)
class _Item:
    source: str
    key: str
    payload: bytes
    arrival_ns: int
    #: the channel's stamp (the writer's), None for a plain sample
    stamp_ns: int | None


def _header(payload: bytes) -> tuple[int, int] | None:
    """(seq, stamp_ns) of an arpz data message (a msgpack array ``[writer, seq, stamp_ns, ...]``)
    or of a report map with ``stamp_ns``; None otherwise."""
    try:
        decoded = msgspec.msgpack.decode(payload)
    except DECODE_ERRORS:
        return None
    if isinstance(decoded, list) and len(decoded) >= 3:
        seq, stamp = decoded[1], decoded[2]
        if isinstance(seq, int) and isinstance(stamp, int):
            return seq, stamp
    if isinstance(decoded, dict) and isinstance(decoded.get("stamp_ns"), int):
        return 0, decoded["stamp_ns"]
    return None


def _robot_of(key: str) -> str:
    parsed = keys.parse_robot_key(key)
    return parsed[0] if parsed else ""


class Recorder:
    """Records one fleet into an ``McapSink``. Thread: ``run`` writes; callbacks only queue.

    ``include_internal``: keep arpz's own messages that have no standard ROS 2 type (the Hello
    probe, samples of a topic no announcement named) as JSON channels, instead of leaving them
    out. ``read_only``: read without writing anything to the fleet (BEST_EFFORT readers); None:
    decide from the CEDDP's stats (on under access control)."""

    def __init__(
        self,
        transport: Transport,
        fleet: str,
        sink: McapSink,
        *,
        patterns: Sequence[str] = (),
        traffic: TrafficQos | None = None,
        mode: str | None = None,
        camera_size: tuple[int, int] | None = None,
        mode_wait_s: float = _MODE_WAIT_S,
        include_internal: bool = False,
        read_only: bool | None = None,
        stats_wait_s: float = _STATS_WAIT_S,
        clock_ns: Callable[[], int] = time.time_ns,
        types: MessageTypes | None = None,
    ) -> None:
        self.transport = transport
        self.fleet = fleet
        self.sink = sink
        self.patterns = list(patterns)
        self.traffic = traffic or TrafficQos()
        self.mode = mode
        #: (width, height) of the fleet's camera frames; None: guessed from each frame's length
        self.camera_size = camera_size
        self.mode_wait_s = mode_wait_s
        self.include_internal = include_internal
        self.read_only = read_only
        #: why read_only is what it is (said in the summary)
        self.read_only_reason = "--read-only" if read_only else ""
        self.stats_wait_s = stats_wait_s
        self._clock_ns = clock_ns
        self._queue: queue.Queue[_Item] = queue.Queue(_QUEUE_LIMIT)
        self._lock = threading.Lock()
        self.tallies: dict[str, TopicTally] = {}
        #: (robot, topic) -> sensor kind, from the announcements
        self.kinds: dict[tuple[str, str], str] = {}
        #: (robot, topic) -> a typed sensor's message type, from the announcements
        self.msg_types: dict[tuple[str, str], str] = {}
        #: the message types typed topics are written as (the standard ones, ``--msg-path``'s)
        self.types = types or MessageTypes()
        #: samples of typed topics whose type this recorder does not know, per MCAP topic
        self.unknown_type: dict[str, int] = {}
        #: sensor samples waiting for their announcement: key -> items
        self._pending: dict[str, list[_Item]] = {}
        self._pending_since: dict[str, float] = {}
        #: channel writer guid -> key (from delivered samples), and losses per guid
        self._guid_keys: dict[str, str] = {}
        self._lost_by_guid: dict[str, int] = {}
        #: plain mode: (key, writer) -> last seq seen
        self._last_seq: dict[tuple[str, str], int] = {}
        #: losses reported by a writer no sample of which arrived (its key is unknown)
        self.unattributed_lost = 0
        self.skipped = 0
        self.unknown_keys = 0
        #: arpz's own messages left out (no ``include_internal``), per MCAP topic
        self.left_out: dict[str, int] = {}
        self._readers: list[Reader] = []
        self._frames: FrameReader | None = None
        self._handles: list[Handle] = []
        self._modes: dict[str, str] = {}
        self.started_ns = 0

    # -- opening ----------------------------------------------------------------------------

    def _on_mode(self, key: str, alive: bool) -> None:
        if alive:
            with self._lock:
                self._modes[key] = key.rsplit("/", 1)[-1]

    def decide_mode(self) -> str:
        """The fleet's mode: the CEDDP's token, else the robots' (all alike), else channel."""
        fleet = self.fleet
        ceddp_prefix = f"{keys.fleet_prefix(fleet)}/ceddp/mode/"
        self._handles.append(
            self.transport.watch_liveliness(keys.all_ceddp_modes(fleet), self._on_mode)
        )
        self._handles.append(
            self.transport.watch_liveliness(keys.all_robot_modes(fleet), self._on_mode)
        )
        wait_s = self.mode_wait_s
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline:
            with self._lock:
                if any(k.startswith(ceddp_prefix) for k in self._modes):
                    break
            time.sleep(0.02)
        with self._lock:
            ceddp = {m for k, m in self._modes.items() if k.startswith(ceddp_prefix)}
            robots = {m for k, m in self._modes.items() if not k.startswith(ceddp_prefix)}
        if len(ceddp) == 1:
            return ceddp.pop()
        if len(robots) == 1:
            return robots.pop()
        log.warning("no CEDDP mode token within %.1f s: recording through the channel", wait_s)
        return "channel"

    def decide_read_only(self, ceddp_present: bool) -> bool:
        """Read only when the CEDDP reports access control in force: the recorder then holds an
        observer's certificate at most, whose rights refuse a reader's token and ACKNACKs, so a
        RELIABLE reader would never be matched and would record nothing."""
        if not ceddp_present:
            self.read_only_reason = "no CEDDP seen: access control unknown"
            return False
        watch = CeddpStatsWatch(self.transport, self.fleet)
        try:
            stats = watch.wait(self.stats_wait_s)
        finally:
            watch.close()
        if stats is None:
            self.read_only_reason = f"no CEDDP stats within {self.stats_wait_s:g} s"
            return False
        if stats.access_control:
            self.read_only_reason = "the CEDDP reports access control in force"
            return True
        self.read_only_reason = "the CEDDP reports no access control"
        return False

    def _reader_profile(self, profile: QosProfile) -> QosProfile:
        """What the recorder asks for: the fleet's profile, or read-only BEST_EFFORT VOLATILE
        (matches every writer, sends no ACKNACK, no history is replayed to it)."""
        if not self.read_only:
            return profile
        return msgspec.structs.replace(
            profile,
            reliability=ReliabilityPolicy.BEST_EFFORT,
            durability=DurabilityPolicy.VOLATILE,
        )

    def start(self) -> None:
        """Decide the mode, then open every reader and liveliness watch."""
        self.mode = self.mode or self.decide_mode()
        if self.read_only is None:
            with self._lock:
                ceddp = any("/ceddp/mode/" in k for k in self._modes)
            self.read_only = self.mode == "channel" and self.decide_read_only(ceddp)
        fleet, t = self.fleet, self.traffic
        prefix = keys.fleet_prefix(fleet)
        exprs = {
            SENSOR: keys.all_sensors(fleet),
            COMMAND: f"{prefix}/robot/*/cmd/*",
            REPORT: keys.all_reports(fleet),
        }
        profiles = {
            SENSOR: t.sensor_qos,
            COMMAND: t.command_qos,
            REPORT: t.report_qos,
        }
        self.started_ns = self._clock_ns()
        for source, expr in exprs.items():
            if self.mode == "channel":
                self._readers.append(
                    Reader(
                        self.transport,
                        expr,
                        self._reader_profile(profiles[source]),
                        self._data_callback(source),
                        events=ReaderEventCallbacks(message_lost=self._on_lost),
                    )
                )
            else:
                self._handles.append(self.transport.subscribe(expr, self._plain_callback(source)))
        if self.mode == "channel":
            self._frames = FrameReader(
                self.transport,
                keys.all_frames(fleet),
                self._reader_profile(t.frames_qos),
                self._on_frame,
                max_frame_bytes=LARGE_SAMPLE_BYTES,
            )
        for expr in (keys.all_presence(fleet), keys.all_robot_modes(fleet)):
            self._handles.append(self.transport.watch_liveliness(expr, self._on_token))

    # -- callbacks: only queue ----------------------------------------------------------------

    def _put(self, item: _Item) -> None:
        self._queue.put(item)

    def _data_callback(self, source: str) -> Callable[[bytes, DataInfo], None]:
        def on_data(payload: bytes, info: DataInfo) -> None:
            with self._lock:
                self._guid_keys.setdefault(info.writer, info.key)
            self._put(_Item(source, info.key, payload, self._clock_ns(), info.stamp_ns))

        return on_data

    def _plain_callback(self, source: str) -> Callable[[str, bytes, bytes | None], None]:
        def on_sample(key: str, payload: bytes, attachment: bytes | None) -> None:
            self._put(_Item(source, key, payload, self._clock_ns(), None))

        return on_sample

    def _on_frame(self, payload: bytes, info: FrameInfo) -> None:
        self._put(_Item(FRAME, info.key, payload, self._clock_ns(), info.stamp_ns))

    def _on_lost(self, status: MessageLostStatus) -> None:
        with self._lock:
            guid = status.writer
            self._lost_by_guid[guid] = self._lost_by_guid.get(guid, 0) + status.total_count_change

    def _on_token(self, key: str, alive: bool) -> None:
        now = self._clock_ns()
        self._put(_Item(LIVELINESS, key, msgspec.msgpack.encode(alive), now, now))

    # -- the writing thread ---------------------------------------------------------------------

    def run(self, stop: threading.Event, duration_s: float = 0.0) -> None:
        """Write what arrives until ``stop`` is set or ``duration_s`` (0: no limit) passed."""
        end = time.monotonic() + (duration_s or float("inf"))
        while not stop.is_set() and time.monotonic() < end:
            try:
                item = self._queue.get(timeout=min(0.1, max(end - time.monotonic(), 0.001)))
            except queue.Empty:
                self._flush_unannounced(force=False)
                continue
            self._handle(item)
            if not self._queue.qsize():
                self._flush_unannounced(force=False)

    def close(self) -> list[Path]:
        """Stop reading, write what is queued and pending, close the files; the files."""
        for reader in self._readers:
            reader.close()
        if self._frames is not None:
            self._frames.close()
        for handle in self._handles:
            handle.undeclare()
        while True:
            try:
                self._handle(self._queue.get_nowait())
            except queue.Empty:
                break
        self._flush_unannounced(force=True)
        self._attribute_losses()
        return self.sink.finish()

    def _selected(self, topic: Topic) -> bool:
        """Announcements and liveliness are always recorded (play needs them); the patterns
        select among the rest, matched against the MCAP topic or the arpz key."""
        return topic.kind in ("announce", LIVELINESS) or matches(topic, self.patterns)

    def _tally(
        self,
        key: str,
        robot: str,
        kind: str,
        source: str,
        command_type: str | None = None,
        msg_type: str | None = None,
    ) -> TopicTally | None:
        """The tally of ``key``'s channel, made on its first message (None: not selected)."""
        tally = self.tallies.get(key)
        if tally is not None:
            return tally
        t = self.traffic
        channel = self.mode == "channel"
        qos: QosProfile | None = {
            SENSOR: t.sensor_qos,
            FRAME: t.frames_qos,
            COMMAND: t.command_qos,
            REPORT: t.report_qos,
            LIVELINESS: None,
        }[source]
        if kind == "hello":
            qos = t.hello_qos or t.sensor_qos
        definition = self.types.definition(msg_type) if msg_type is not None else ""
        topic = Topic(
            key, robot, kind, qos if channel else None, command_type, msg_type, definition
        )
        if not self._selected(topic):
            self.skipped += 1
            return None
        tally = self.tallies[key] = TopicTally(topic)
        return tally

    def _handle(self, item: _Item) -> None:
        parsed = keys.parse_robot_key(item.key)
        if parsed is None:
            self.unknown_keys += 1
            return
        robot, what, name = parsed
        if item.source == LIVELINESS:
            self._liveliness(item, robot)
        elif item.source in (SENSOR, FRAME):
            self._sensor(item, robot, name)
        elif item.source == COMMAND:
            if name == keys.HELLO:
                self._internal(item, robot, "hello")
            else:
                self._command(item, robot)
        else:
            kind = report_kind(what)
            if kind is None or name:
                self.unknown_keys += 1
                return
            self._report(item, robot, what, kind)

    def _learn_kinds(self, announce: Announce, robot: str) -> None:
        for info in announce.sensors:
            self.kinds[(robot, info.topic)] = info.kind
            if info.msg_type:
                self.msg_types[(robot, info.topic)] = info.msg_type
        for key in [k for k in self._pending if _robot_of(k) == robot]:
            for waiting in self._pending.pop(key):
                self._handle(waiting)
            self._pending_since.pop(key, None)

    def _flush_unannounced(self, *, force: bool) -> None:
        now = time.monotonic()
        for key in list(self._pending):
            if force or now - self._pending_since[key] >= _UNANNOUNCED_WAIT_S:
                for item in self._pending.pop(key):
                    self._internal(item, _robot_of(key), self._raw_sample_kind(item))
                del self._pending_since[key]

    def _raw_sample_kind(self, item: _Item) -> str:
        """``sample`` or ``large_sample`` (a camera frame or point cloud) for a sample recorded
        as it came; a key keeps the kind of its channel."""
        tally = self.tallies.get(item.key)
        if tally is not None:
            return tally.topic.kind
        if item.source == FRAME:
            return "large_sample"
        try:
            SAMPLE_DECODER.decode(item.payload)
        except DECODE_ERRORS:
            return "large_sample"
        return "sample"

    def _sensor(self, item: _Item, robot: str, name: str) -> None:
        if name == keys.HELLO:
            self._internal(item, robot, "hello")
            return
        kind = self.kinds.get((robot, name))
        if kind is None:
            if item.key in self.tallies:  # recorded raw already: stay on that channel
                self._internal(item, robot, self.tallies[item.key].topic.kind)
                return
            self._pending_since.setdefault(item.key, time.monotonic())
            self._pending.setdefault(item.key, []).append(item)
            return
        if kind == MESSAGE_KIND:
            self._typed(item, robot, name)
            return
        if kind not in SENSOR_KINDS:  # a kind with no ROS 2 type: recorded as it came
            self._internal(item, robot, self._raw_sample_kind(item))
            return
        tally = self._tally(item.key, robot, kind, item.source)
        if tally is None:
            return
        try:
            decoder = LARGE_SAMPLE_DECODER if kind in LARGE_KINDS else SAMPLE_DECODER
            sample = decoder.decode(item.payload)
            size = self.camera_size
            if not (
                isinstance(sample.value, bytes)
                and size
                and size[0] * size[1] * 3 == len(sample.value)
            ):
                size = None
            data = to_cdr(
                kind, sample.value, stamp_ns=sample.stamp_ns, frame_id=f"{robot}/{name}", size=size
            )
        except (*DECODE_ERRORS, ConversionError) as exc:
            self._undecodable(tally, item, exc)
            return
        if not is_exact(kind, sample.value):
            tally.rounded += 1
        self._count_plain_gap(item.key, sample.writer, sample.seq, tally)
        self._write(tally, item, data, log_ns=sample.stamp_ns, sequence=sample.seq)

    def _typed(self, item: _Item, robot: str, name: str) -> None:
        """A typed sensor's message, written as CDR of its own type (the MCAP channel's schema
        is the type's definition); a type this recorder does not know is counted, not written."""
        msg_type = self.msg_types.get((robot, name))
        if msg_type is None or not self.types.known(msg_type):
            topic = f"/{robot}/{name}"
            self.unknown_type[topic] = self.unknown_type.get(topic, 0) + 1
            throttled.warning(
                f"unknown type {topic}",
                "%s: type %s unknown to this recorder: not recorded (give its folder with "
                "--msg-path)",
                topic,
                msg_type,
            )
            return
        tally = self._tally(item.key, robot, MESSAGE_KIND, item.source, msg_type=msg_type)
        if tally is None:
            return
        try:
            large = msg_type in LARGE_TYPES
            sample = (LARGE_SAMPLE_DECODER if large else MESSAGE_SAMPLE_DECODER).decode(
                item.payload
            )
            data = self.types.to_cdr(msg_type, self.types.decode(msg_type, sample.value))
        except DECODE_ERRORS as exc:
            self._undecodable(tally, item, exc)
            return
        self._count_plain_gap(item.key, sample.writer, sample.seq, tally)
        self._write(tally, item, data, log_ns=sample.stamp_ns, sequence=sample.seq)

    def _undecodable(self, tally: TopicTally, item: _Item, exc: Exception) -> None:
        tally.undecodable += 1
        throttled.warning(f"undecodable {item.key}", "%s: not recorded: %s", item.key, exc)

    def _write(
        self, tally: TopicTally, item: _Item, data: bytes, *, log_ns: int, sequence: int
    ) -> None:
        tally.messages += 1
        tally.bytes += len(data)
        self.sink.write(
            tally.topic, data, log_ns=log_ns, publish_ns=item.arrival_ns, sequence=sequence
        )

    def _command(self, item: _Item, robot: str) -> None:
        """A CEDDP command as the standard type of its value (the channel's first command's)."""
        try:
            command = COMMAND_DECODER.decode(item.payload)
            ros_type = command_type(command.value)
        except (*DECODE_ERRORS, ConversionError) as exc:
            tally = self._tally(item.key, robot, "command", COMMAND)
            if tally is not None:
                self._undecodable(tally, item, exc)
            return
        tally = self._tally(item.key, robot, "command", COMMAND, ros_type)
        if tally is None:
            return
        try:
            data = command_cdr(command.value, tally.topic.command_type or ros_type)
        except ConversionError as exc:
            self._undecodable(tally, item, exc)
            return
        self._write(tally, item, data, log_ns=command.stamp_ns, sequence=command.seq)

    def _report(self, item: _Item, robot: str, what: str, kind: str) -> None:
        """A robot's report as a DiagnosticArray of its fields."""
        tally = self._tally(item.key, robot, kind, REPORT)
        if tally is None:
            return
        try:
            report = msgspec.msgpack.decode(item.payload, type=REPORT_MESSAGES[kind])
            stamp_ns = getattr(report, "stamp_ns", None) or item.stamp_ns or item.arrival_ns
            summary, level = _report_summary(report)
            data = report_cdr(
                report,
                name=f"{robot}/{what}",
                hardware_id=robot,
                summary=summary,
                stamp_ns=stamp_ns,
                level=level,
            )
        except (*DECODE_ERRORS, msgspec.ValidationError, ConversionError) as exc:
            self._undecodable(tally, item, exc)
            return
        if isinstance(report, Announce):
            self._learn_kinds(report, robot)
        self._write(tally, item, data, log_ns=stamp_ns, sequence=getattr(report, "seq", 0))

    def _liveliness(self, item: _Item, robot: str) -> None:
        tally = self._tally(item.key, robot, LIVELINESS, LIVELINESS)
        if tally is None:
            return
        alive = bool(msgspec.msgpack.decode(item.payload))
        data = liveliness_report(tally.topic, alive, item.arrival_ns)
        self._write(tally, item, data, log_ns=item.arrival_ns, sequence=0)

    def _internal(self, item: _Item, robot: str, kind: str) -> None:
        """arpz's own message with no ROS 2 type: JSON with ``include_internal``, else left out
        (counted per topic)."""
        if not self.include_internal:
            name = Topic(item.key, robot, kind, None).name
            self.left_out[name] = self.left_out.get(name, 0) + 1
            return
        source = COMMAND if kind == "hello" and "/cmd/" in item.key else item.source
        tally = self._tally(item.key, robot, kind, source)
        if tally is None:
            return
        try:
            message = msgspec.msgpack.decode(item.payload, type=INTERNAL_MESSAGES[kind])
            assert isinstance(message, Hello | Sample | LargeSample | Command)
            data = internal_json(kind, message)
        except (*DECODE_ERRORS, msgspec.ValidationError) as exc:
            self._undecodable(tally, item, exc)
            return
        if isinstance(message, Sample | LargeSample):
            self._count_plain_gap(item.key, message.writer, message.seq, tally)
        self._write(tally, item, data, log_ns=message.stamp_ns, sequence=message.seq)

    def _count_plain_gap(self, key: str, writer: str, seq: int, tally: TopicTally) -> None:
        """Plain mode has no channel: a gap in the payload's seq of one writer is a loss."""
        if self.mode == "channel":
            return
        last = self._last_seq.get((key, writer))
        if last is not None and seq > last + 1:
            tally.lost += seq - last - 1
        if last is None or seq > last:
            self._last_seq[(key, writer)] = seq

    def _attribute_losses(self) -> None:
        with self._lock:
            lost = dict(self._lost_by_guid)
            guid_keys = dict(self._guid_keys)
        for guid, count in lost.items():
            key = guid_keys.get(guid)
            if key is not None and key in self.tallies:
                self.tallies[key].lost += count
            else:
                self.unattributed_lost += count

    # -- the summary ----------------------------------------------------------------------------

    def summary(self) -> dict[str, Any]:
        topics = {
            t.topic.name: {
                "key": t.topic.key,
                "kind": t.topic.kind,
                "type": t.topic.type_name,
                "encoding": t.topic.encoding,
                "messages": t.messages,
                "bytes": t.bytes,
                "lost": t.lost,
                "rounded": t.rounded,
                "undecodable": t.undecodable,
            }
            for t in sorted(self.tallies.values(), key=lambda t: t.topic.name)
        }
        channel: dict[str, Any] = {}
        for reader in self._readers:
            s = reader.stats()
            channel[reader.key_expr] = {
                "delivered": s.delivered,
                "lost": s.lost,
                "retransmitted": s.retransmitted,
                "lifespan_expired": s.lifespan_expired,
            }
        if self._frames is not None:
            frames = self._frames.stats()
            channel[self._frames.key_expr] = {
                "frames": msgspec.to_builtins(frames.frames),
                "fragments_lost": frames.channel.lost,
                "fragments_retransmitted": frames.channel.retransmitted,
            }
        return {
            "fleet": self.fleet,
            "mode": self.mode,
            "read_only": bool(self.read_only),
            "read_only_reason": self.read_only_reason,
            "include_internal": self.include_internal,
            "files": [str(p) for p in self.sink.files],
            "duration_s": round((self._clock_ns() - self.started_ns) / 1e9, 3),
            "messages": sum(t.messages for t in self.tallies.values()),
            "lost": sum(t.lost for t in self.tallies.values()) + self.unattributed_lost,
            "unattributed_lost": self.unattributed_lost,
            "skipped_by_pattern": self.skipped,
            "unknown_keys": self.unknown_keys,
            "internal_left_out": dict(sorted(self.left_out.items())),
            "unknown_type": dict(sorted(self.unknown_type.items())),
            "topics": topics,
            "channel": channel,
        }


def _report_summary(report: msgspec.Struct) -> tuple[str, int]:
    """The DiagnosticStatus message and level of a robot's report: one sentence, and WARN for
    what ``arpz doctor`` would warn about in it (INCOMPATIBLE_QOS, a refused QoS assignment,
    a collision)."""
    if isinstance(report, Announce):
        return (
            f"{len(report.sensors)} sensor(s), {len(report.commands)} command(s), "
            f"{report.mode} mode",
            OK,
        )
    if isinstance(report, RobotStats):
        what = "final report" if report.final else "report"
        if report.incompatible_qos:
            return f"{what}: INCOMPATIBLE_QOS: {'; '.join(report.incompatible_qos)}", WARN
        return f"{what}: {sum(t.sent for t in report.topics.values())} samples sent", OK
    if isinstance(report, QosAck):
        level = OK if report.status == "applied" else WARN
        return f"QoS epoch {report.epoch} {report.status}: {report.reason}".rstrip(": "), level
    assert isinstance(report, Telemetry)
    where = f"x {report.x_m:.2f} m, y {report.y_m:.2f} m, theta {report.theta_rad:.2f} rad"
    return (f"collided at {where}", WARN) if report.collided else (where, OK)


def format_summary(summary: dict[str, Any]) -> str:
    rows = [("topic", "type", "messages", "lost", "rounded", "undecodable")]
    for name, t in summary["topics"].items():
        rows.append(
            (name, t["type"], str(t["messages"]), str(t["lost"]), str(t["rounded"]),
             str(t["undecodable"]))
        )  # fmt: skip
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in rows]
    files = ", ".join(summary["files"])
    read_only = ", read-only" if summary["read_only"] else ""
    lines.append(
        f"{summary['messages']} messages in {summary['duration_s']:.1f} s ({summary['mode']} "
        f"mode{read_only}), {summary['lost']} lost during the recording -> {files}"
    )
    left_out = summary["internal_left_out"]
    if left_out:
        lines.append(
            f"left out {sum(left_out.values())} of arpz's own messages with no ROS 2 type "
            f"({', '.join(f'{n} {t}' for t, n in left_out.items())}): --include-internal "
            "keeps them as JSON"
        )
    unknown = summary["unknown_type"]
    if unknown:
        lines.append(
            f"not recorded: {sum(unknown.values())} messages of typed topics whose type this "
            f"recorder does not know ({', '.join(f'{n} {t}' for t, n in unknown.items())}): "
            "--msg-path gives it the fleet's own .msg files"
        )
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m arpz record",
        description="Record a running fleet's sensor topics, commands and robot reports into "
        "MCAP (the rosbag2 profile, every channel a standard ROS 2 type in CDR: ROS 2 tools and "
        "Foxglove read it whole). Stops on SIGINT or after --duration, then prints messages and "
        "losses per topic.",
    )
    startup.add_fleet_client_options(parser)
    parser.add_argument("--out", required=True, type=Path, metavar="FILE.mcap")
    parser.add_argument("--duration", type=float, default=0.0, metavar="S", help="0: until SIGINT")
    parser.add_argument(
        "--split-size", type=float, default=0.0, metavar="MB", help="start FILE_1.mcap ... past MB"
    )
    parser.add_argument(
        "--split-duration", type=float, default=0.0, metavar="S", help="a new file every S"
    )
    parser.add_argument(
        "--camera-size",
        default=None,
        metavar="WIDTHxHEIGHT",
        help="the cameras' frame size (default: guessed from a frame's length, 640x480 and "
        "other common sizes; else one row of pixels)",
    )
    parser.add_argument(
        "--qos-from",
        type=Path,
        metavar="TOML",
        help="the fleet's CEDDP (or a robot's) config: read with its [*_qos] profiles and store "
        "them as each topic's QoS (default: arpz's default profiles, which a fleet that changed "
        "them does not use)",
    )
    parser.add_argument(
        "--msg-path",
        action="append",
        default=[],
        metavar="DIR",
        help="a folder of the fleet's own .msg files (PACKAGE/msg/NAME.msg; repeatable): their "
        "typed topics are recorded as their own types (standard ROS 2 types need nothing)",
    )
    parser.add_argument(
        "--include-internal",
        action="store_true",
        help="also keep arpz's own messages that have no ROS 2 type (the Hello probe, samples of "
        "a topic no announcement named) as schemaless JSON channels, which MCAP readers and "
        "Foxglove decode and ROS 2 tools skip",
    )
    parser.add_argument(
        "--read-only",
        action="store_true",
        help="write nothing to the fleet: BEST_EFFORT readers, no ACKNACK, no resend (default: "
        "so when the CEDDP reports access control in force, as an observer's certificate "
        "requires)",
    )
    startup.add_json_option(parser, "the summary")
    startup.add_version_option(parser)
    parser.add_argument(
        "patterns",
        nargs="*",
        metavar="TOPIC_PATTERN",
        help="record only these (shell patterns on '/robot1/lidar_0' or the arpz key; the "
        "robots' announcements and presence are always recorded)",
    )
    return parser


def _camera_size(text: str | None) -> tuple[int, int] | None:
    if text is None:
        return None
    width, _, height = text.lower().partition("x")
    if not (width.isdigit() and height.isdigit() and int(width) > 0 and int(height) > 0):
        raise ArpzError(f"--camera-size {text!r}: give WIDTHxHEIGHT in pixels, e.g. 640x480")
    return int(width), int(height)


def _fleet_traffic(path: Path | None) -> TrafficQos | None:
    """The QoS profiles of the fleet's own config file (a CEDDP's, else a robot's): the
    liveliness tokens carry reliability, durability and deadline but not history and depth, so
    the recorded QoS can only be the fleet's exactly when its config is given."""
    if path is None:
        return None
    try:
        return load_toml(path, CeddpConfig)
    except ConfigError as as_ceddp:
        try:
            return load_toml(path, RobotConfig)
        except ConfigError:
            raise as_ceddp from None


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        endpoints = startup.connect_endpoints(args.connect)
        keys.check_chunk(args.fleet, what="--fleet")
        if args.duration < 0 or args.split_size < 0 or args.split_duration < 0:
            raise ArpzError("--duration, --split-size and --split-duration must be >= 0")
        camera_size = _camera_size(args.camera_size)
        traffic = _fleet_traffic(args.qos_from)
        if args.out.suffix != ".mcap":
            raise ArpzError(f"--out {args.out}: give a file name ending in .mcap")
        types = MessageTypes()
        types.add_msg_paths(args.msg_path)
    except ArpzError as exc:
        return startup.fail("record", str(exc))
    startup.configure_logging("WARNING")
    stop = startup.stop_on_signals()
    try:
        transport = open_client(endpoints, args.zenoh_config)
    except TransportError as exc:
        return startup.fail("record", str(exc), 1)
    sink = McapSink(
        args.out,
        split_bytes=int(args.split_size * 2**20),
        split_s=args.split_duration,
        metadata={"fleet": args.fleet, "arpz_version": arpz_version()},
    )
    recorder = Recorder(
        transport,
        args.fleet,
        sink,
        traffic=traffic,
        patterns=args.patterns,
        camera_size=camera_size,
        include_internal=args.include_internal,
        types=types,
        read_only=True if args.read_only else None,
    )
    try:
        recorder.start()
        read_only = f", read-only: {recorder.read_only_reason}" if recorder.read_only else ""
        print(
            f"recording fleet '{args.fleet}' from {','.join(endpoints)} ({recorder.mode} mode"
            f"{read_only}) into {args.out}",
            file=sys.stderr,
            flush=True,
        )
        recorder.run(stop, args.duration)
    finally:
        try:
            recorder.close()
        finally:
            transport.close()
    summary = recorder.summary()
    print(
        format_summary(summary),
        file=sys.stderr if args.json == startup.JSON_TO_STDOUT else sys.stdout,
    )
    startup.emit_json(summary, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
