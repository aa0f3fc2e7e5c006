"""``arpz record``: a running fleet into MCAP files that ROS 2 tools and Foxglove open.

``Recorder`` joins the fleet as one more reader of every robot's sensor topics, frames, reports
and commands, through the reliable channel when the fleet runs it (the CEDDP's mode token says
so) and as a plain subscriber otherwise, so what it could not get is counted by the channel and
said in the summary, never lost silently. It learns each topic's kind from the robots'
announcements and writes each key as one MCAP channel (arpz.tools._recording gives the
layout). The channel callbacks only queue; one thread (``run``) converts and writes.

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
    CeddpConfig,
    ConfigError,
    RobotConfig,
    TrafficQos,
    load_toml,
)
from arpz.core.errors import ArpzError
from arpz.core.messages import (
    ANNOUNCE_DECODER,
    DECODE_ERRORS,
    LARGE_SAMPLE_DECODER,
    SAMPLE_DECODER,
)
from arpz.core.protocol.qos import QosProfile
from arpz.core.rosmsg.convert import ConversionError, is_exact, to_cdr
from arpz.core.throttled_log import ThrottledLog
from arpz.core.transport import Handle, Transport, TransportError
from arpz.core.version import arpz_version
from arpz.runtime import startup
from arpz.tools._recording import McapSink, Topic, matches, open_client, report_kind

log = logging.getLogger(__name__)
throttled = ThrottledLog(log)

#: how long a sensor sample waits for the announcement that names its topic's kind before it is
#: recorded as a raw arpz Sample
_UNANNOUNCED_WAIT_S = 3.0
#: how long the recorder waits for the CEDDP's mode token before it decides the mode
_MODE_WAIT_S = 2.0
#: samples waiting for the writing thread; beyond, the channel's readers wait (backpressure:
#: the channel recovers or counts what it then cannot deliver)
_QUEUE_LIMIT = 100_000

SENSOR, FRAME, COMMAND, REPORT, LIVELINESS = "sensor", "frame", "command", "report", "liveliness"


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
    """Records one fleet into an ``McapSink``. Thread: ``run`` writes; callbacks only queue."""

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
        clock_ns: Callable[[], int] = time.time_ns,
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
        self._clock_ns = clock_ns
        self._queue: queue.Queue[_Item] = queue.Queue(_QUEUE_LIMIT)
        self._lock = threading.Lock()
        self.tallies: dict[str, TopicTally] = {}
        #: (robot, topic) -> sensor kind, from the announcements
        self.kinds: dict[tuple[str, str], str] = {}
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

    def start(self) -> None:
        """Decide the mode, then open every reader and liveliness watch."""
        self.mode = self.mode or self.decide_mode()
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
                        profiles[source],
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
                t.frames_qos,
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
        return topic.kind in ("announce", "liveliness") or matches(topic, self.patterns)

    def _topic(self, key: str, robot: str, kind: str, source: str) -> Topic | None:
        tally = self.tallies.get(key)
        if tally is not None:
            return tally.topic
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
        topic = Topic(key, robot, kind, qos if channel else None)
        if not self._selected(topic):
            self.skipped += 1
            return None
        self.tallies[key] = TopicTally(topic)
        return topic

    def _handle(self, item: _Item) -> None:
        parsed = keys.parse_robot_key(item.key)
        if parsed is None:
            self.unknown_keys += 1
            return
        robot, what, name = parsed
        if item.source == LIVELINESS:
            self._write_raw(item, robot, "liveliness", sequence=0, stamp_ns=item.arrival_ns)
        elif item.source in (SENSOR, FRAME):
            self._sensor(item, robot, name)
        elif item.source == COMMAND:
            self._write_raw(item, robot, "hello" if name == keys.HELLO else "command")
        else:
            kind = report_kind(what)
            if kind is None or name:
                self.unknown_keys += 1
                return
            if kind == "announce":
                self._announce(item, robot)
            self._write_raw(item, robot, kind)

    def _announce(self, item: _Item, robot: str) -> None:
        try:
            announce = ANNOUNCE_DECODER.decode(item.payload)
        except DECODE_ERRORS as exc:
            throttled.warning(f"announce {robot}", "undecodable announcement of %s: %s", robot, exc)
            return
        for info in announce.sensors:
            self.kinds[(robot, info.topic)] = info.kind
        for key in [k for k in self._pending if _robot_of(k) == robot]:
            for waiting in self._pending.pop(key):
                self._handle(waiting)
            self._pending_since.pop(key, None)

    def _flush_unannounced(self, *, force: bool) -> None:
        now = time.monotonic()
        for key in list(self._pending):
            if force or now - self._pending_since[key] >= _UNANNOUNCED_WAIT_S:
                for item in self._pending.pop(key):
                    self._write_raw(item, _robot_of(key), "sample")
                del self._pending_since[key]

    def _sensor(self, item: _Item, robot: str, name: str) -> None:
        if name == keys.HELLO:
            self._write_raw(item, robot, "hello")
            return
        kind = self.kinds.get((robot, name))
        if kind is None:
            if item.key in self.tallies:  # recorded raw already: stay on that channel
                self._write_raw(item, robot, self.tallies[item.key].topic.kind)
                return
            self._pending_since.setdefault(item.key, time.monotonic())
            self._pending.setdefault(item.key, []).append(item)
            return
        topic = self._topic(item.key, robot, kind, item.source)
        if topic is None:
            return
        tally = self.tallies[item.key]
        if not topic.standard:
            self._write_raw(item, robot, topic.kind)
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
            tally.undecodable += 1
            throttled.warning(
                f"undecodable {item.key}", "%s: sample not recorded: %s", item.key, exc
            )
            return
        if not is_exact(kind, sample.value):
            tally.rounded += 1
        self._count_plain_gap(item.key, sample.writer, sample.seq, tally)
        tally.messages += 1
        tally.bytes += len(data)
        self.sink.write(
            topic, data, log_ns=sample.stamp_ns, publish_ns=item.arrival_ns, sequence=sample.seq
        )

    def _write_raw(
        self,
        item: _Item,
        robot: str,
        kind: str,
        *,
        sequence: int | None = None,
        stamp_ns: int | None = None,
    ) -> None:
        topic = self._topic(item.key, robot, kind, item.source)
        if topic is None:
            return
        tally = self.tallies[item.key]
        if stamp_ns is None:
            header = _header(item.payload)
            if header is None:
                sequence, stamp_ns = 0, item.stamp_ns or item.arrival_ns
            else:
                sequence, stamp_ns = header
        tally.messages += 1
        tally.bytes += len(item.payload)
        self.sink.write(
            topic,
            item.payload,
            log_ns=stamp_ns,
            publish_ns=item.arrival_ns,
            sequence=sequence or 0,
        )

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
            "files": [str(p) for p in self.sink.files],
            "duration_s": round((self._clock_ns() - self.started_ns) / 1e9, 3),
            "messages": sum(t.messages for t in self.tallies.values()),
            "lost": sum(t.lost for t in self.tallies.values()) + self.unattributed_lost,
            "unattributed_lost": self.unattributed_lost,
            "skipped_by_pattern": self.skipped,
            "unknown_keys": self.unknown_keys,
            "topics": topics,
            "channel": channel,
        }


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
    lines.append(
        f"{summary['messages']} messages in {summary['duration_s']:.1f} s ({summary['mode']} "
        f"mode), {summary['lost']} lost during the recording -> {files}"
    )
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m arpz record",
        description="Record a running fleet's sensor topics and commands into MCAP (the rosbag2 "
        "profile: ROS 2 tools and Foxglove open it). Stops on SIGINT or after --duration, then "
        "prints messages and losses per topic.",
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
    )
    try:
        recorder.start()
        print(
            f"recording fleet '{args.fleet}' from {','.join(endpoints)} ({recorder.mode} mode) "
            f"into {args.out}",
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
