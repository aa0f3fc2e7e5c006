"""``arpz play``: a recording published back into a fleet as if its robots were there.

The CEDDP, its planner and the QoS optimiser can then run without robots. ``Player`` does what
a robot agent does on the wire, with the agent's own building blocks (``Outlet`` and
``FrameOutlet`` with the recorded QoS, ``keys`` for every key, the arpz messages): it declares
each robot's presence and mode tokens when the recording saw them appear, and publishes its
announcements, sensor samples, Hello probes and telemetry on the same keys, with the original
timing scaled by ``--rate``. Every replayed message is stamped anew on the way out (the
recorded stamp shifted to now, in the same scale), so a planner judging the age of data sees
the ages the robots' data had; a replay is a new incarnation of each robot (its ``writer`` and
``incarnation``), numbering what it sends from 1 as a restarted robot would.

Not published: the CEDDP's commands (``cmd/*``, the CEDDP under test sends its own: compare
them with the recorded ones), and the robots' stats and QoS acks (they count what the recorded
robots did, and answered a CEDDP that is not there).

Every form ``arpz record`` writes is read back (``arpz.tools._recording.recorded_message``): the
ROS 2 messages of sensor topics, the DiagnosticArrays of the announcements, telemetry and
liveliness tokens, the JSON of the Hello probes and raw samples (``--include-internal``), and
the msgpack of recordings made before issue 41.

Usage: ``python -m arpz play FILE.mcap [--rate FACTOR] [--loop] [--topics PATTERN ...]``
(docs/tools.md "Recording and replay").
"""

from __future__ import annotations

import argparse
import logging
import struct
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Schema

from arpz.channel.io import FrameOutlet, Outlet
from arpz.core import keys
from arpz.core.config import LARGE_SAMPLE_BYTES, LARGE_TYPES, MESSAGE_KIND, SENSOR_KINDS
from arpz.core.errors import ArpzError
from arpz.core.messages import (
    DECODE_ERRORS,
    Announce,
    Hello,
    LargeSample,
    MessageSample,
    Sample,
    Telemetry,
    encode,
    new_incarnation,
    writer_id,
)
from arpz.core.msgtypes import MessageTypes
from arpz.core.protocol.qos import QosProfile
from arpz.core.rosmsg.convert import ConversionError, from_cdr
from arpz.core.throttled_log import ThrottledLog
from arpz.core.transport import Handle, Transport, TransportError
from arpz.runtime import startup
from arpz.tools._recording import LIVELINESS, Topic, matches, open_client, recorded_message

log = logging.getLogger(__name__)
throttled = ThrottledLog(log)

#: channel kinds published back (sensor kinds too); the others are recorded for reading only
PLAYED_KINDS = frozenset(
    {*SENSOR_KINDS, "sample", "large_sample", "hello", "telemetry", "announce"}
)
#: how long play waits for the fleet's readers (the CEDDP) to match its writers before it starts
MATCH_TIMEOUT_S = 5.0
#: how long the writers wait for the last messages' acknowledgement at the end
_CLOSE_WAIT_S = 2.0


class RecordingError(ArpzError, ValueError):
    """A file that is not an arpz recording (or not MCAP); the message names the file."""


@dataclass
class Played:
    """What play did with one recorded key."""

    topic: Topic
    published: int = 0
    #: messages that could not be decoded or converted back (counted, not published)
    undecodable: int = 0
    #: refused by a full KEEP_ALL history
    write_failures: int = 0


@dataclass
class _RobotState:
    incarnation: str = field(default_factory=new_incarnation)
    tokens: dict[str, Handle] = field(default_factory=dict)


def _topic(metadata: dict[str, str], fleet: str | None) -> Topic | None:
    """The recorded key of a channel, moved to ``fleet`` when given; None if not arpz's."""
    key, kind = metadata.get("arpz_key"), metadata.get("arpz_kind")
    if not key or not kind:
        return None
    parsed = keys.parse_robot_key(key)
    if parsed is None:
        return None
    if fleet is not None:
        key = f"{keys.fleet_prefix(fleet)}/{key.split('/', 2)[2]}"
    raw_qos = metadata.get("arpz_qos", "none")
    qos = None if raw_qos == "none" else msgspec.json.decode(raw_qos, type=QosProfile)
    msg_type = metadata.get("arpz_type") if kind == MESSAGE_KIND else None
    return Topic(key, parsed[0], kind, qos, msg_type=msg_type)


def recorded_fleet(path: Path) -> str:
    """The fleet a recording was made of (its ``arpz`` metadata record)."""
    with path.open("rb") as stream:
        for record in make_reader(stream).iter_metadata():
            if record.name == "arpz" and "fleet" in record.metadata:
                return record.metadata["fleet"]
    raise RecordingError(f"{path}: no 'arpz' metadata record: not made by arpz record")


class Player:
    """Publishes recordings into a fleet. Thread: ``run`` publishes on the calling thread."""

    def __init__(
        self,
        transport: Transport,
        files: Sequence[Path],
        *,
        fleet: str | None = None,
        rate: float = 1.0,
        loop: bool = False,
        patterns: Sequence[str] = (),
    ) -> None:
        if not rate > 0:
            raise ArpzError(f"--rate must be > 0, got {rate}")
        self.transport = transport
        self.files = list(files)
        self.fleet = fleet
        self.rate = rate
        self.loop = loop
        self.patterns = list(patterns)
        self.played: dict[str, Played] = {}
        self._robots: dict[str, _RobotState] = {}
        self._outlets: dict[str, Outlet | FrameOutlet] = {}
        #: the typed topics' message types, learnt from the recording's schemas
        self.types = MessageTypes()
        self._seqs: dict[str, int] = {}
        self.loops = 0
        self._start_wall_ns = time.time_ns()
        self.first_ns, self.last_ns = self._span()

    # -- the recording ----------------------------------------------------------------------

    def _span(self) -> tuple[int, int]:
        first, last = None, None
        for path in self.files:
            try:
                with path.open("rb") as stream:
                    stats = make_reader(stream).get_summary()
            except (OSError, McapError, ValueError, struct.error) as exc:
                raise RecordingError(f"{path}: not a readable MCAP file: {exc}") from None
            if stats is None or stats.statistics is None:
                raise RecordingError(f"{path}: no MCAP summary (was the recording cut short?)")
            s = stats.statistics
            if s.message_count:
                first = min(first or s.message_start_time, s.message_start_time)
                last = max(last or s.message_end_time, s.message_end_time)
        if first is None or last is None:
            raise RecordingError(f"{', '.join(map(str, self.files))}: the recording is empty")
        return first, last

    def _messages(self) -> Iterator[tuple[Topic, str, int, bytes]]:
        """(topic, message encoding, log time, data) of every recorded message, in order."""
        for path in self.files:
            with path.open("rb") as stream:
                topics: dict[int, Topic | None] = {}
                for schema, channel, message in make_reader(stream).iter_messages(
                    log_time_order=True
                ):
                    if channel.id not in topics:
                        topics[channel.id] = _topic(channel.metadata, self.fleet)
                        self._learn_type(topics[channel.id], schema)
                    topic = topics[channel.id]
                    if topic is not None:
                        yield topic, channel.message_encoding, message.log_time, message.data

    def _learn_type(self, topic: Topic | None, schema: Schema | None) -> None:
        """A typed topic's type from the recording's own schema (its ``.msg`` definition, a
        team's own types too): play needs no ``.msg`` files."""
        if topic is None or not topic.typed or schema is None or topic.msg_type is None:
            return
        if not self.types.known(topic.msg_type):
            self.types.add_definition(topic.msg_type, schema.data.decode())

    def _selected(self, topic: Topic) -> bool:
        if topic.kind in (LIVELINESS, "announce"):
            return True
        if topic.typed:
            return matches(topic, self.patterns)
        return topic.kind in PLAYED_KINDS and matches(topic, self.patterns)

    # -- opening the writers ------------------------------------------------------------------

    def _outlet(self, topic: Topic) -> Outlet | FrameOutlet:
        outlet = self._outlets.get(topic.key)
        if outlet is None:
            if topic.qos is not None and "/frames/" in topic.key:
                outlet = FrameOutlet(self.transport, topic.key, topic.qos, LARGE_SAMPLE_BYTES)
            else:
                outlet = Outlet(self.transport, topic.key, topic.qos)
            self._outlets[topic.key] = outlet
        return outlet

    def open(self, match_timeout_s: float = MATCH_TIMEOUT_S) -> None:
        """Open a writer for every played key and wait (bounded) until a reader matched each:
        a VOLATILE writer's first samples reach only readers matched when they are written."""
        topics: dict[str, Topic] = {}
        for path in self.files:
            with path.open("rb") as stream:
                summary = make_reader(stream).get_summary()
            for channel in summary.channels.values() if summary else ():
                topic = _topic(channel.metadata, self.fleet)
                if topic is not None and topic.kind != LIVELINESS and self._selected(topic):
                    topics.setdefault(topic.key, topic)
        # a robot is played when one of its data topics is (its announcement alone is not)
        robots = {t.robot for t in topics.values() if t.kind != "announce"}
        for key, topic in sorted(topics.items()):
            if topic.robot in robots:
                self.played[key] = Played(topic)
                self._outlet(topic)
        self._robots = {robot: _RobotState() for robot in sorted(robots)}
        deadline = time.monotonic() + match_timeout_s
        while time.monotonic() < deadline and not all(o.matched for o in self._outlets.values()):
            time.sleep(0.02)
        unmatched = [key for key, o in self._outlets.items() if not o.matched]
        if unmatched:
            log.warning(
                "no reader matched %d key(s) within %.1f s (is a CEDDP running for this fleet?):"
                " %s",
                len(unmatched),
                match_timeout_s,
                ", ".join(unmatched[:3]),
            )

    # -- publishing -----------------------------------------------------------------------------

    def run(self, stop: threading.Event) -> None:
        """Publish the recording (again and again with ``loop``) until it ends or ``stop``."""
        span_ns = self.last_ns - self.first_ns + 1
        while not stop.is_set():
            start_mono = time.monotonic()
            self._start_wall_ns = time.time_ns()
            for topic, encoding, log_ns, data in self._messages():
                offset_s = (log_ns - self.first_ns) / 1e9 / self.rate
                if startup.wait_for_stop(stop, start_mono + offset_s - time.monotonic()):
                    return
                self._publish(topic, encoding, log_ns, data)
            self.loops += 1
            if not self.loop:
                return
            # the next pass starts one recording span after this one began
            startup.wait_for_stop(stop, start_mono + span_ns / 1e9 / self.rate - time.monotonic())

    def _restamp(self, stamp_ns: int) -> int:
        """A recorded stamp moved to this pass: as long after its start as it was after the
        recording's, scaled by the rate."""
        return self._start_wall_ns + int((stamp_ns - self.first_ns) / self.rate)

    def _publish(self, topic: Topic, encoding: str, log_ns: int, data: bytes) -> None:
        robot = self._robots.get(topic.robot)
        if robot is None:
            return
        if topic.kind == LIVELINESS:
            try:
                alive = recorded_message(topic, encoding, data)
            except (*DECODE_ERRORS, ConversionError) as exc:
                throttled.warning(f"token {topic.name}", "%s: not played: %s", topic.name, exc)
                return
            self._token(robot, topic.key, alive)
            return
        played = self.played.get(topic.key)
        if played is None:
            return
        writer = writer_id(topic.robot, robot.incarnation)
        try:
            payload, stamp_ns = self._payload(
                topic, encoding, data, log_ns, writer, robot.incarnation
            )
        except (*DECODE_ERRORS, ConversionError, msgspec.ValidationError) as exc:
            played.undecodable += 1
            throttled.warning(f"undecodable {topic.name}", "%s: not played: %s", topic.name, exc)
            return
        if self._outlet(topic).send(payload, stamp_ns):
            played.published += 1
        else:
            played.write_failures += 1

    def _typed_payload(
        self, topic: Topic, data: bytes, log_ns: int, writer: str
    ) -> tuple[bytes, int]:
        """A typed topic's CDR message as the robot sends it: a ``MessageSample`` (a
        ``LargeSample`` of the message's bytes for an image or point cloud), stamped with its
        header's stamp (or the log time) moved to this pass."""
        assert topic.msg_type is not None
        message = self.types.from_cdr(topic.msg_type, data)
        header = getattr(message, "header", None)
        stamp_ns = log_ns
        if header is not None and hasattr(header, "stamp"):
            stamp_ns = header.stamp.sec * 1_000_000_000 + header.stamp.nanosec
        stamp = self._restamp(stamp_ns)
        seq = self._next_seq(topic.key)
        raw = self.types.encode(message)
        if topic.msg_type in LARGE_TYPES:
            return encode(LargeSample(writer, seq, stamp, raw)), stamp
        return encode(MessageSample(writer, seq, stamp, msgspec.Raw(raw))), stamp

    def _next_seq(self, key: str) -> int:
        seq = self._seqs[key] = self._seqs.get(key, 0) + 1
        return seq

    def _payload(
        self, topic: Topic, encoding: str, data: bytes, log_ns: int, writer: str, incarnation: str
    ) -> tuple[bytes, int]:
        """The message as the robot would send it now: re-stamped, numbered by this writer."""
        kind, restamp = topic.kind, self._restamp
        if topic.typed:
            return self._typed_payload(topic, data, log_ns, writer)
        if kind in SENSOR_KINDS:
            seq = self._next_seq(topic.key)
            reading = from_cdr(kind, data)
            # std_msgs/msg/Bool has no header: its stamp is the log time
            stamp = restamp(log_ns if reading.stamp_ns is None else reading.stamp_ns)
            value = reading.value
            message: msgspec.Struct = (
                LargeSample(writer, seq, stamp, value)
                if isinstance(value, bytes)
                else Sample(writer, seq, stamp, value)
            )
            return encode(message), stamp
        recorded = recorded_message(topic, encoding, data)
        if isinstance(recorded, Announce):
            again_announce = msgspec.structs.replace(recorded, incarnation=incarnation)
            return encode(again_announce), time.time_ns()
        seq = self._next_seq(topic.key)
        if isinstance(recorded, Sample | LargeSample):
            stamp = restamp(recorded.stamp_ns)
            again = msgspec.structs.replace(
                recorded, writer=writer, seq=seq, stamp_ns=stamp, changed_ns=0, since_ns=0
            )
            return encode(again), stamp
        if isinstance(recorded, Hello):
            stamp = restamp(recorded.stamp_ns)
            again_hello = msgspec.structs.replace(
                recorded, writer=writer, seq=seq, stamp_ns=stamp, t0_ns=restamp(recorded.t0_ns)
            )
            return encode(again_hello), stamp
        if isinstance(recorded, Telemetry):
            stamp = restamp(recorded.stamp_ns)
            return encode(
                msgspec.structs.replace(recorded, writer=writer, seq=seq, stamp_ns=stamp)
            ), stamp
        raise ConversionError(f"a {kind} message is not played")

    def _token(self, robot: _RobotState, key: str, alive: bool) -> None:
        handle = robot.tokens.get(key)
        if alive and handle is None:
            robot.tokens[key] = self.transport.declare_token(key)
        elif not alive and handle is not None:
            robot.tokens.pop(key).undeclare()

    def close(self) -> None:
        """Wait (bounded) for the last messages' acknowledgements, close the writers, and let
        the robots leave (their tokens vanish)."""
        for outlet in self._outlets.values():
            outlet.close(_CLOSE_WAIT_S)
        for robot in self._robots.values():
            for handle in robot.tokens.values():
                handle.undeclare()
            robot.tokens.clear()

    def summary(self) -> dict[str, Any]:
        return {
            "files": [str(p) for p in self.files],
            "rate": self.rate,
            "loops": self.loops,
            "robots": sorted(self._robots),
            "published": sum(p.published for p in self.played.values()),
            "topics": {
                p.topic.name: {
                    "key": p.topic.key,
                    "published": p.published,
                    "undecodable": p.undecodable,
                    "write_failures": p.write_failures,
                }
                for p in sorted(self.played.values(), key=lambda p: p.topic.name)
            },
        }


def recording_files(path: Path) -> list[Path]:
    """``path``, or the split files ``{stem}_0.mcap``, ``{stem}_1.mcap``, ... recorded for it."""
    if path.exists():
        return [path]
    files: list[Path] = []
    while (split := path.with_name(f"{path.stem}_{len(files)}{path.suffix}")).exists():
        files.append(split)
    if not files:
        raise RecordingError(f"{path}: no such recording (nor {path.stem}_0{path.suffix})")
    return files


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m arpz play",
        description="Publish a recording made by 'arpz record' into a fleet as if its robots "
        "were there: same keys, the recorded timing, through the reliable channel with the "
        "recorded QoS.",
    )
    parser.add_argument(
        "file",
        type=Path,
        metavar="FILE.mcap",
        help="a recording (or the name given to --out when it was split into FILE_0.mcap ...)",
    )
    startup.add_fleet_client_options(
        parser,
        fleet_default=None,
        fleet_help="publish into this fleet (default: the fleet the recording was made of)",
    )
    parser.add_argument(
        "--rate", type=float, default=1.0, metavar="FACTOR", help="2: twice as fast"
    )
    parser.add_argument("--loop", action="store_true", help="start again at the end, until SIGINT")
    parser.add_argument(
        "--topics", nargs="+", default=[], metavar="PATTERN", help="play only these topics"
    )
    startup.add_json_option(parser, "what was published")
    startup.add_version_option(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        endpoints = startup.connect_endpoints(args.connect)
        files = recording_files(args.file)
        fleet = args.fleet or recorded_fleet(files[0])
        keys.check_chunk(fleet, what="--fleet")
    except ArpzError as exc:
        return startup.fail("play", str(exc))
    startup.configure_logging("WARNING")
    stop = startup.stop_on_signals()
    try:
        transport = open_client(endpoints, args.zenoh_config)
    except TransportError as exc:
        return startup.fail("play", str(exc), 1)
    try:
        player = Player(
            transport, files, fleet=fleet, rate=args.rate, loop=args.loop, patterns=args.topics
        )
        player.open()
        print(
            f"playing {len(files)} file(s) of {(player.last_ns - player.first_ns) / 1e9:.1f} s "
            f"into fleet '{fleet}' on {','.join(endpoints)} at x{args.rate:g}",
            file=sys.stderr,
            flush=True,
        )
        player.run(stop)
        player.close()
    except ArpzError as exc:
        return startup.fail("play", str(exc))
    finally:
        transport.close()
    summary = player.summary()
    print(
        f"published {summary['published']} messages of {len(summary['robots'])} robots "
        f"({summary['loops']} pass(es))",
        file=sys.stderr,
    )
    startup.emit_json(summary, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
