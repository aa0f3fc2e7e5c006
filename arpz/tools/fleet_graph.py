"""The graph of a running fleet: its nodes (robots, the CEDDP), its topics, and who writes and
reads each, discovered only from what the fleet already publishes.

Nothing here asks the fleet anything. Three sources are enough:

- liveliness tokens (``arpz/{fleet}/**``): the robots' and the CEDDP's presence and mode tokens,
  and the reliable channel's writer and reader tokens ``{topic}/rel/{w|r}/{guid}/{qos}``, whose
  last chunk is the matching part of each endpoint's QoS (docs/reliability.md, "Keys");
- each robot's ``Announce`` (its sensor topics with kind, rate and value type, and the commands it
  acts on), which is also how plain-mode topics (``reliability = "none"``, no tokens) are found;
- each robot's ``RobotStats`` (measured send rates, the downlink's delivered counters).

``FleetObserver`` is the pure part: observations in, a ``FleetGraph`` out (unit-tested without
Zenoh). ``discover`` is the I/O part: it watches the three sources on a transport for a short
while and returns the graph. ``arpz topic`` uses both; ``arpz doctor`` can reuse them.

Topic names follow ROS 2 (``/robot1/lidar``, ``/robot1/cmd/velocity``, ``/ceddp/stats``); each
maps to exactly one arpz key (``topic_name`` and ``resolve``).
"""

from __future__ import annotations

import contextlib
import difflib
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Final

from arpz.bridge.rmw_zenoh import ADMIN_SPACE, GraphRecord, graph_records
from arpz.channel import DurabilityPolicy, Reader
from arpz.core import keys
from arpz.core.config import LARGE_KINDS, LARGE_TYPES, MESSAGE_KIND
from arpz.core.errors import ArpzError
from arpz.core.messages import (
    ANNOUNCE_DECODER,
    CEDDP_STATS_DECODER,
    DECODE_ERRORS,
    STATS_DECODER,
    Announce,
    CeddpStats,
    RobotStats,
)
from arpz.core.protocol import wire
from arpz.core.protocol.qos import (
    MatchQos,
    QosPolicyKind,
    QosProfile,
    decode_match_qos,
    incompatible_policy,
)
from arpz.core.rosmsg.types import UnknownKindError, ros_types_for
from arpz.core.transport import Handle, Transport

#: the single-chunk report keys below ``robot/{robot}/`` and their payload types
ROBOT_REPORTS: Final = {
    "stats": "RobotStats",
    "announce": "Announce",
    "qos": "QosAck",
    "telemetry": "Telemetry",
}
#: the CEDDP's keys below ``ceddp/`` and their payload types
CEDDP_KEYS: Final = {
    "stats": "CeddpStats",
    "qos": "QosAssignmentMsg",
    "qos/request": "any (a trigger)",
}
#: the node name of the CEDDP in topic names and writer columns
CEDDP: Final = "ceddp"
#: what a writer or reader of a plain-mode key shows as its QoS
PLAIN: Final = "plain"


class UnknownTopicError(ArpzError, LookupError):
    """A topic the fleet does not have; the message lists the closest names."""


# ----------------------------------------------------------------------------- topic names


def topic_name(fleet: str, key: str) -> str | None:
    """The ROS 2 style name of an arpz key, or None for a key that is not a topic (tokens,
    control keys of the channel, other fleets)."""
    prefix = f"{keys.ROOT}/{fleet}/"
    if not key.startswith(prefix):
        return None
    parts = key[len(prefix) :].split("/")
    if parts[0] == "robot" and len(parts) >= 3:
        robot, rest = parts[1], parts[2:]
        if len(rest) == 2 and rest[0] in ("sensor", "frames"):
            return f"/{robot}/{rest[1]}"
        if len(rest) == 2 and rest[0] == "cmd":
            return f"/{robot}/cmd/{rest[1]}"
        if len(rest) == 1 and rest[0] in ROBOT_REPORTS:
            return f"/{robot}/{rest[0]}"
        return None
    if parts[0] == CEDDP and "/".join(parts[1:]) in CEDDP_KEYS:
        return "/" + "/".join(parts)
    return None


def payload_type(fleet: str, key: str, kind: str | None, msg_type: str | None = None) -> str:
    """The arpz message type (arpz/core/messages.py) carried on ``key``."""
    parsed = keys.parse_robot_key(key)
    if parsed is not None:
        _, section, name = parsed
        if name == keys.HELLO and section in ("sensor", "cmd"):
            return "Hello"
        large = kind in LARGE_KINDS or msg_type in LARGE_TYPES
        if section == "frames" or (section == "sensor" and large):
            return "LargeSample"
        if section == "sensor" and kind == MESSAGE_KIND:
            return "MessageSample"
        if section == "sensor":
            return "Sample"
        if section == "cmd":
            return "Command"
        return ROBOT_REPORTS.get(section, "?")
    rest = key.removeprefix(f"{keys.fleet_prefix(fleet)}/{CEDDP}/")
    return CEDDP_KEYS.get(rest, "?")


# ----------------------------------------------------------------------------- the graph


@dataclass(frozen=True)
class Endpoint:
    """One writer or reader of a topic: a channel endpoint (guid and the QoS its token carries)
    or a plain Zenoh publisher (``guid`` "" and ``qos`` None)."""

    node: str
    guid: str
    qos: MatchQos | None

    @property
    def plain(self) -> bool:
        return self.qos is None

    def describe_qos(self) -> str:
        return describe_match_qos(self.qos)

    def as_dict(self) -> dict[str, object]:
        return {
            "node": self.node,
            "guid": self.guid or None,
            "qos": match_qos_dict(self.qos),
        }


def describe_match_qos(qos: MatchQos | None) -> str:
    """``RELIABLE VOLATILE`` (+ deadline, liveliness, lease when set), or ``plain``."""
    if qos is None:
        return PLAIN
    words = [
        "RELIABLE" if qos.reliable else "BEST_EFFORT",
        "TRANSIENT_LOCAL" if qos.transient_local else "VOLATILE",
    ]
    if qos.deadline_us:
        words.append(f"deadline {qos.deadline_us / 1e6:g}s")
    if qos.manual:
        words.append("MANUAL_BY_TOPIC")
    if qos.lease_us:
        words.append(f"lease {qos.lease_us / 1e6:g}s")
    return " ".join(words)


def match_qos_dict(qos: MatchQos | None) -> dict[str, object] | None:
    if qos is None:
        return None
    return {
        "reliability": "reliable" if qos.reliable else "best_effort",
        "durability": "transient_local" if qos.transient_local else "volatile",
        "liveliness": "manual_by_topic" if qos.manual else "automatic",
        "deadline_s": qos.deadline_us / 1e6,
        "lease_duration_s": qos.lease_us / 1e6,
    }


@dataclass(frozen=True)
class TopicEntry:
    """One topic of the fleet, as ``topic list`` and ``topic info`` show it."""

    name: str
    key: str
    #: the node that writes it (a robot id, or "ceddp")
    owner: str
    #: the arpz payload type (arpz/core/messages.py): Sample, LargeSample, Command, RobotStats, ...
    arpz_type: str
    #: the msgpack type of a Sample's or Command's value ("float", "bool", "str", "bytes"), or None
    value_type: str | None
    #: the sensor kind (lidar, camera, ..., "message" for a typed sensor) from the robot's
    #: announcement, or None
    kind: str | None
    #: the standard ROS 2 types of a sensor topic's readings (the topic's own first), or ()
    ros_types: tuple[str, ...]
    #: "channel" or "none" (the owner's mode), None when unknown
    mode: str | None
    #: the rate the robot announced (its configuration, or the QoS assignment in force)
    announced_rate_hz: float | None
    #: measured by the writer over its last reporting interval (messages actually sent)
    measured_rate_hz: float | None
    writers: tuple[Endpoint, ...]
    readers: tuple[Endpoint, ...]
    #: the depth of the QoS assignment in force on a sensor topic (None: the robot's config)
    assigned_depth: int | None = None
    #: a typed sensor's ROS 2 message type and its RIHS01 hash, as the robot announced them
    msg_type: str | None = None
    type_hash: str | None = None

    @property
    def ros_type(self) -> str | None:
        return self.ros_types[0] if self.ros_types else None

    @property
    def large(self) -> bool:
        return self.arpz_type == "LargeSample"

    @property
    def reliable_channel(self) -> bool:
        """Some writer of the topic runs the reliable channel (else: plain Zenoh puts)."""
        return any(not w.plain for w in self.writers) or (not self.writers and self.mode != "none")

    def as_dict(self) -> dict[str, object]:
        return {
            "name": self.name,
            "key": self.key,
            "owner": self.owner,
            "type": self.ros_type,
            "ros_types": list(self.ros_types),
            "arpz_type": self.arpz_type,
            "value_type": self.value_type,
            "kind": self.kind,
            "type_hash": self.type_hash,
            "mode": self.mode,
            "announced_rate_hz": self.announced_rate_hz,
            "measured_rate_hz": self.measured_rate_hz,
            "assigned_depth": self.assigned_depth,
            "writers": [w.as_dict() for w in self.writers],
            "readers": [r.as_dict() for r in self.readers],
        }


@dataclass(frozen=True)
class Node:
    """A robot or the CEDDP: present (its presence token exists) and its mode."""

    name: str
    role: str
    alive: bool
    mode: str | None
    incarnation: str | None = None

    def as_dict(self) -> dict[str, object]:
        return {
            "name": self.name,
            "role": self.role,
            "alive": self.alive,
            "mode": self.mode,
            "incarnation": self.incarnation,
        }


@dataclass(frozen=True)
class FleetGraph:
    fleet: str
    nodes: tuple[Node, ...]
    topics: tuple[TopicEntry, ...]
    #: the latest report of each robot (for rates and clock offsets)
    stats: dict[str, RobotStats] = field(default_factory=dict)
    #: other fleets whose tokens were seen on the same router (a hint for a wrong --fleet)
    other_fleets: tuple[str, ...] = ()
    #: the ROS 2 graph on the same router (rmw_zenoh's liveliness tokens, any domain): the
    #: bridge's publishers and subscriptions and those of ROS 2 nodes (docs/ros2.md)
    ros2: tuple[GraphRecord, ...] = ()
    #: the CEDDP's latest report (None: none heard); its ``access_control`` says whether this
    #: tool may write anything to the fleet (``read_only``)
    ceddp_stats: CeddpStats | None = None

    @property
    def read_only(self) -> bool:
        """The CEDDP reports access control in force: a tool holds an observer's rights at
        most (deploy/tls/make_fleet_certs.py), and must read in a way that writes nothing."""
        return bool(self.ceddp_stats is not None and self.ceddp_stats.access_control)

    def topic(self, name_or_key: str) -> TopicEntry:
        """The topic given as ``/robot1/lidar``, ``robot1/lidar`` or an arpz key
        (``arpz/{fleet}/robot/robot1/sensor/lidar``); ``UnknownTopicError`` naming the closest
        names otherwise."""
        return resolve(self, name_or_key)

    def as_dict(self) -> dict[str, object]:
        return {
            "fleet": self.fleet,
            "nodes": [n.as_dict() for n in self.nodes],
            "topics": [t.as_dict() for t in self.topics],
            "other_fleets": list(self.other_fleets),
            "ros2": [
                {
                    "node": r.node,
                    "topic": r.topic,
                    "type": r.ros_type,
                    "role": r.role,
                    "qos": r.qos.describe(),
                }
                for r in self.ros2
            ],
        }


def matches(topic: TopicEntry) -> list[dict[str, object]]:
    """Every writer x reader pair of a topic with its verdict (arpz.core.protocol.qos matching); a
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


def resolve(graph: FleetGraph, given: str) -> TopicEntry:
    """Find a topic by ROS name (with or without the leading '/') or by its arpz key. A name two
    topics share (a sensor called ``stats``) is refused with both keys, which always work."""
    text = given.strip()
    by_key = text.startswith(f"{keys.ROOT}/")
    wanted = text if by_key else "/" + text.strip("/")
    found = [t for t in graph.topics if (t.key if by_key else t.name) == wanted]
    if len(found) == 1:
        return found[0]
    if found:
        both = ", ".join(t.key for t in found)
        raise UnknownTopicError(f"{given!r} names {len(found)} topics ({both}): give the arpz key")
    candidates = [t.key if by_key else t.name for t in graph.topics]
    close = difflib.get_close_matches(wanted, candidates, n=5, cutoff=0.5)
    hint = f"; did you mean {', '.join(close)}?" if close else ""
    if not graph.topics:
        hint = f"; fleet {graph.fleet!r} has no topics (is --fleet right?{_fleets_hint(graph)})"
    raise UnknownTopicError(f"no topic {given!r} in fleet {graph.fleet!r}{hint}")


def _fleets_hint(graph: FleetGraph) -> str:
    if not graph.other_fleets:
        return ""
    return f" this router also carries: {', '.join(graph.other_fleets)}"


# ----------------------------------------------------------------------------- the observer


class FleetObserver:
    """Accumulates what the fleet publishes (tokens, announcements, stats) and builds the
    ``FleetGraph``. Thread-safe: the callbacks of ``discover`` feed it from Zenoh's threads.

    ``ignore_guids``: this process's own channel endpoints (discovery's readers), left out of
    the graph."""

    def __init__(self, fleet: str) -> None:
        self.fleet = fleet
        self._prefix = f"{keys.fleet_prefix(fleet)}/"
        self._lock = threading.Lock()
        self._tokens: set[str] = set()
        self._announces: dict[str, Announce] = {}
        #: the last two reports of each robot (rates from their difference), same incarnation
        self._stats: dict[str, list[RobotStats]] = {}
        self._other_fleets: set[str] = set()
        self._ros2_tokens: set[str] = set()
        self._ceddp_stats: CeddpStats | None = None
        self.ignore_guids: set[str] = set()
        #: reports that could not be decoded
        self.decode_errors = 0

    # -- observations ---------------------------------------------------------------------------

    def on_ros2_token(self, key: str, alive: bool) -> None:
        """An rmw_zenoh liveliness token (``@ros2_lv/...``): the ROS 2 side of the router."""
        with self._lock:
            if alive:
                self._ros2_tokens.add(key)
            else:
                self._ros2_tokens.discard(key)

    def on_ceddp_stats(self, stats: CeddpStats) -> None:
        with self._lock:
            if self._ceddp_stats is None or stats.stamp_ns >= self._ceddp_stats.stamp_ns:
                self._ceddp_stats = stats

    def ceddp_stats(self) -> CeddpStats | None:
        with self._lock:
            return self._ceddp_stats

    def on_token(self, key: str, alive: bool) -> None:
        if not key.startswith(self._prefix):
            parts = key.split("/")
            if len(parts) > 2 and parts[0] == keys.ROOT:
                with self._lock:
                    self._other_fleets.add(parts[1])
            return
        with self._lock:
            if alive:
                self._tokens.add(key)
            else:
                self._tokens.discard(key)

    def on_report(self, key: str, payload: bytes) -> None:
        """A robot's announce or stats payload (through the channel or plain)."""
        parsed = keys.parse_robot_key(key)
        if parsed is None or not key.startswith(self._prefix):
            return
        robot, section, _ = parsed
        try:
            if section == "announce":
                announce = ANNOUNCE_DECODER.decode(payload)
                with self._lock:
                    self._announces[robot] = announce
            elif section == "stats":
                self.add_stats(robot, STATS_DECODER.decode(payload))
        except DECODE_ERRORS:
            with self._lock:
                self.decode_errors += 1

    def add_stats(self, robot: str, stats: RobotStats) -> None:
        """Keep the two newest reports of the robot's newest incarnation, whatever order they
        come in (the channel's history and the plain subscription race each other)."""
        with self._lock:
            known = self._stats.setdefault(robot, [])
            if known and known[-1].incarnation != stats.incarnation:
                if stats.stamp_ns < known[-1].stamp_ns:
                    return  # an older incarnation's report
                known.clear()
            if any(s.stamp_ns == stats.stamp_ns for s in known):
                return  # the same report twice
            known.append(stats)
            known.sort(key=lambda s: s.stamp_ns)
            del known[:-2]

    def announced(self, robot: str) -> bool:
        with self._lock:
            return robot in self._announces

    def present_robots(self) -> list[str]:
        with self._lock:
            tokens = list(self._tokens)
        return sorted(
            parsed[0]
            for key in tokens
            if (parsed := keys.parse_robot_key(key)) is not None and parsed[1] == "presence"
        )

    def ceddp_present(self) -> bool:
        with self._lock:
            return f"{self._prefix}{CEDDP}/presence" in self._tokens

    def stats_count(self, robot: str) -> int:
        with self._lock:
            return len(self._stats.get(robot, []))

    # -- the graph ------------------------------------------------------------------------------

    def graph(self) -> FleetGraph:
        with self._lock:
            tokens = sorted(self._tokens)
            announces = dict(self._announces)
            stats = {robot: list(pair) for robot, pair in self._stats.items() if pair}
            other = tuple(sorted(self._other_fleets - {self.fleet}))
            ros2, _not_rmw_zenoh = graph_records(sorted(self._ros2_tokens))
            ceddp_stats = self._ceddp_stats
        nodes = self._nodes(tokens, announces, stats)
        modes = {node.name: node.mode for node in nodes}
        writers: dict[str, list[Endpoint]] = {}
        readers: dict[str, list[Endpoint]] = {}
        for key in tokens:
            for kind, into in (("w", writers), ("r", readers)):
                split = wire.split_control_key(key, kind, 2)
                if split is None:
                    continue
                topic, (guid, chunk) = split
                if guid in self.ignore_guids or topic_name(self.fleet, topic) is None:
                    continue
                qos = decode_match_qos(chunk)
                if qos is None:
                    continue
                node = (
                    owner_of(self.fleet, topic) if kind == "w" else reader_node(self.fleet, topic)
                )
                into.setdefault(topic, []).append(Endpoint(node, guid, qos))
        topic_keys = set(writers) | set(readers)
        for robot, announce in announces.items():
            topic_keys.update(announced_keys(self.fleet, robot, announce))
        for robot in stats:
            topic_keys.add(keys.stats_key(self.fleet, robot))
        if any(node.name == CEDDP and node.alive for node in nodes):
            topic_keys.add(keys.ceddp_stats_key(self.fleet))  # a plain CEDDP has no token
        topics = [
            self._entry(key, writers, readers, announces, stats, modes)
            for key in sorted(topic_keys)
        ]
        latest = {robot: pair[-1] for robot, pair in stats.items()}
        return FleetGraph(
            self.fleet,
            tuple(nodes),
            tuple(sorted(topics, key=lambda t: t.name)),
            latest,
            other,
            tuple(sorted(ros2, key=lambda r: (r.topic, r.role, r.node))),
            ceddp_stats,
        )

    def _nodes(
        self,
        tokens: list[str],
        announces: dict[str, Announce],
        stats: dict[str, list[RobotStats]],
    ) -> list[Node]:
        present: set[str] = set()
        modes: dict[str, str] = {}
        ceddp_alive = False
        ceddp_mode: str | None = None
        for key in tokens:
            parsed = keys.parse_robot_key(key)
            if parsed is not None:
                robot, section, name = parsed
                if section == "presence":
                    present.add(robot)
                elif section == "mode" and name:
                    modes[robot] = name
                continue
            rest = key[len(self._prefix) :]
            if rest == f"{CEDDP}/presence":
                ceddp_alive = True
            elif rest.startswith(f"{CEDDP}/mode/"):
                ceddp_mode = rest.rsplit("/", 1)[-1]
        robots = sorted(present | set(announces) | set(stats))
        nodes = []
        if ceddp_alive or ceddp_mode is not None:
            nodes.append(Node(CEDDP, "ceddp", ceddp_alive, ceddp_mode))
        for robot in robots:
            announce = announces.get(robot)
            mode = modes.get(robot) or (announce.mode if announce else None)
            incarnation = stats[robot][-1].incarnation if robot in stats else None
            if incarnation is None and announce is not None:
                incarnation = announce.incarnation
            nodes.append(Node(robot, "robot", robot in present, mode, incarnation))
        return nodes

    def _entry(
        self,
        key: str,
        writers: dict[str, list[Endpoint]],
        readers: dict[str, list[Endpoint]],
        announces: dict[str, Announce],
        stats: dict[str, list[RobotStats]],
        modes: dict[str, str | None],
    ) -> TopicEntry:
        name = topic_name(self.fleet, key)
        assert name is not None
        owner = owner_of(self.fleet, key)
        parsed = keys.parse_robot_key(key)
        robot = parsed[0] if parsed else None
        announce = announces.get(robot) if robot else None
        kind = value_type = msg_type = type_hash = None
        announced = measured = None
        depth = None
        report = stats.get(robot, []) if robot else []
        if parsed is not None and parsed[1] in ("sensor", "frames") and parsed[2] != keys.HELLO:
            info = next(
                (s for s in (announce.sensors if announce else []) if s.topic == parsed[2]), None
            )
            if info is not None:
                kind, value_type, announced = info.kind, info.value_type, info.rate_hz
                msg_type, type_hash = info.msg_type or None, info.type_hash or None
            if report:
                counters = report[-1].topics.get(parsed[2])
                measured = counters.rate_hz if counters is not None else None
                depth = report[-1].qos_depth
        elif parsed is not None and parsed[1] == "cmd":
            value_type = "Hello" if parsed[2] == keys.HELLO else "float|bool|str|list[float]"
            measured = inbound_rate(report, f"cmd/{parsed[2]}")
        elif parsed is not None and parsed[1] == "stats" and len(report) == 2:
            measured = _per_second(1, report[0].stamp_ns, report[1].stamp_ns)
        arpz_type = payload_type(self.fleet, key, kind, msg_type)
        if arpz_type == "Hello":
            value_type = None
        ros_types: tuple[str, ...] = (msg_type,) if msg_type else ()
        if kind is not None and not msg_type:
            with contextlib.suppress(UnknownKindError):
                ros_types = ros_types_for(kind)
        mode = modes.get(robot) if robot else modes.get(CEDDP)
        if parsed is not None and parsed[1] == "cmd":
            mode = modes.get(CEDDP) or mode
        topic_writers = list(writers.get(key, []))
        if not topic_writers and mode == "none":
            topic_writers = [Endpoint(owner, "", None)]
        return TopicEntry(
            name=name,
            key=key,
            owner=owner,
            arpz_type=arpz_type,
            value_type=value_type,
            kind=kind,
            ros_types=ros_types,
            mode=mode,
            announced_rate_hz=announced,
            measured_rate_hz=measured,
            writers=tuple(topic_writers),
            readers=tuple(readers.get(key, [])),
            assigned_depth=depth,
            msg_type=msg_type,
            type_hash=type_hash,
        )


def owner_of(fleet: str, key: str) -> str:
    """Who writes ``key``: the robot for its own keys, the CEDDP for commands and its keys."""
    parsed = keys.parse_robot_key(key)
    if parsed is None or parsed[1] == "cmd":
        return CEDDP
    return parsed[0]


def reader_node(fleet: str, key: str) -> str:
    """Who reads ``key`` in an arpz fleet: the robot reads its commands, the CEDDP the rest (a
    tool's reader shows as one more reader of the same node kind: tokens carry no name)."""
    parsed = keys.parse_robot_key(key)
    if parsed is not None and parsed[1] == "cmd":
        return parsed[0]
    if parsed is None and key.endswith(f"/{CEDDP}/qos"):
        return "robots"
    return CEDDP


def announced_keys(fleet: str, robot: str, announce: Announce) -> list[str]:
    """Every key an announcing robot writes or reads: its sensors (large kinds on ``frames/``
    in channel mode), its Hello probe, its reports, and the commands the CEDDP sends it."""
    out = [keys.stats_key(fleet, robot), keys.announce_key(fleet, robot)]
    for sensor in announce.sensors:
        with contextlib.suppress(keys.KeyExprError):
            large = sensor.kind in LARGE_KINDS or sensor.msg_type in LARGE_TYPES
            if large and announce.mode == "channel":
                out.append(keys.frames_key(fleet, robot, sensor.topic))
            else:
                out.append(keys.sensor_key(fleet, robot, sensor.topic))
    out.append(keys.sensor_key(fleet, robot, keys.HELLO))
    for command in announce.commands:
        with contextlib.suppress(keys.KeyExprError):
            out.append(keys.command_key(fleet, robot, command))
    return out


def _per_second(count: float, t0_ns: int, t1_ns: int) -> float | None:
    return count / ((t1_ns - t0_ns) / 1e9) if t1_ns > t0_ns else None


def inbound_rate(report: list[RobotStats], name: str) -> float | None:
    """Messages per second a robot's reader of ``name`` (``cmd/velocity``) delivered between its
    last two reports; None with fewer than two."""
    if len(report) < 2:
        return None
    before, after = report[0].inbound.get(name), report[1].inbound.get(name)
    if before is None or after is None:
        return None
    return _per_second(after.delivered - before.delivered, report[0].stamp_ns, report[1].stamp_ns)


# ----------------------------------------------------------------------------- discovery (I/O)

#: the reports discovery reads: each robot's announcements and stats
_REPORT_SECTIONS: Final = ("announce", "stats")
#: a TRANSIENT_LOCAL reader gets the robots' latest reports (KEEP_LAST 4 histories) at once
_HISTORY_QOS: Final = QosProfile(depth=4, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def watch_reports(
    transport: Transport,
    key_expr: str,
    on_report: Callable[[str, bytes], None],
    handles: list[Handle],
    readers: list[Reader],
) -> Reader:
    """Read the reports on ``key_expr`` both ways (into ``handles`` and ``readers``, which the
    caller closes): a plain subscription, which gets each report as it is published and asks
    nothing of anyone (all an observer's rights allow under access control), and a
    TRANSIENT_LOCAL channel reader, which gets the writers' latest reports at once in a fleet
    without access control (under it, its token and ACKNACKs are refused by the router and it
    stays silent: docs/security.md). The reader, whose guid the caller may leave out of a
    graph."""
    handles.append(transport.subscribe(key_expr, lambda k, p, _a: on_report(k, p)))
    reader = Reader(transport, key_expr, _HISTORY_QOS, lambda p, info: on_report(info.key, p))
    readers.append(reader)
    return reader


class CeddpStatsWatch:
    """The CEDDP's latest ``CeddpStats`` (``watch_reports``), until closed; each one also to
    ``on_stats`` when given (from Zenoh's or the reader's thread)."""

    def __init__(
        self,
        transport: Transport,
        fleet: str,
        on_stats: Callable[[CeddpStats], None] | None = None,
    ) -> None:
        self._on_stats = on_stats
        self._lock = threading.Lock()
        self._latest: CeddpStats | None = None
        self._arrived = threading.Event()
        self._handles: list[Handle] = []
        self._readers: list[Reader] = []
        try:
            watch_reports(
                transport, keys.ceddp_stats_key(fleet), self._on, self._handles, self._readers
            )
        except BaseException:
            self.close()
            raise

    def _on(self, _key: str, payload: bytes) -> None:
        try:
            stats = CEDDP_STATS_DECODER.decode(payload)
        except DECODE_ERRORS:
            return
        with self._lock:
            if self._latest is None or stats.stamp_ns >= self._latest.stamp_ns:
                self._latest = stats
        if self._on_stats is not None:
            self._on_stats(stats)
        self._arrived.set()

    @property
    def guids(self) -> set[str]:
        return {reader.guid for reader in self._readers}

    def latest(self) -> CeddpStats | None:
        with self._lock:
            return self._latest

    def wait(self, timeout_s: float) -> CeddpStats | None:
        """The latest report, waiting up to ``timeout_s`` for a first one."""
        self._arrived.wait(timeout_s)
        return self.latest()

    def close(self) -> None:
        for reader in self._readers:
            reader.close()
        for handle in self._handles:
            handle.undeclare()
        self._readers, self._handles = [], []


class Discovery:
    """Watches a fleet on ``transport`` until closed: liveliness tokens of ``arpz/{fleet}/**``
    (and of ``arpz/**`` for the names of other fleets on the router, which access control
    refuses an observer, harmlessly), the robots' announcements and stats and the CEDDP's stats
    (``watch_reports``). Keeping it open keeps the graph current, which the streaming commands
    use for clock offsets."""

    def __init__(self, transport: Transport, fleet: str) -> None:
        self.observer = FleetObserver(fleet)
        self._handles: list[Handle] = []
        self._readers: list[Reader] = []
        self._ceddp: CeddpStatsWatch | None = None
        try:
            # the fleet's own tokens on their own: a subscription to all of arpz/** is refused
            # whole where access control allows only the fleet's keys (an observer)
            self._handles.append(
                transport.watch_liveliness(f"{keys.fleet_prefix(fleet)}/**", self.observer.on_token)
            )
            self._handles.append(transport.watch_liveliness(f"{keys.ROOT}/**", self._on_any_token))
            self._handles.append(
                transport.watch_liveliness(f"{ADMIN_SPACE}/**", self.observer.on_ros2_token)
            )
            for section in _REPORT_SECTIONS:
                expr = f"{keys.fleet_prefix(fleet)}/robot/*/{section}"
                reader = watch_reports(
                    transport, expr, self.observer.on_report, self._handles, self._readers
                )
                self.observer.ignore_guids.add(reader.guid)
            self._ceddp = CeddpStatsWatch(transport, fleet, self.observer.on_ceddp_stats)
            self.observer.ignore_guids.update(self._ceddp.guids)
        except BaseException:
            self.close()
            raise

    def _on_any_token(self, key: str, alive: bool) -> None:
        """Tokens of every fleet: only other fleets' names are taken from here."""
        if not key.startswith(f"{keys.fleet_prefix(self.observer.fleet)}/"):
            self.observer.on_token(key, alive)

    def settle(
        self, *, min_s: float = 0.3, max_s: float = 3.0, stop: threading.Event | None = None
    ) -> FleetGraph:
        """Wait until every present robot has announced itself and reported twice (or
        ``max_s``, or ``stop``), at least ``min_s`` (the tokens' history); return the graph."""
        start = time.monotonic()
        while stop is None or not stop.is_set():
            elapsed = time.monotonic() - start
            robots = self.observer.present_robots()
            done = (
                elapsed >= min_s
                and all(
                    self.observer.announced(r) and self.observer.stats_count(r) >= 2 for r in robots
                )
                and (self.observer.ceddp_stats() is not None or not self.observer.ceddp_present())
            )
            if done or elapsed >= max_s:
                break
            time.sleep(0.05)
        return self.observer.graph()

    def graph(self) -> FleetGraph:
        return self.observer.graph()

    def close(self) -> None:
        if self._ceddp is not None:
            self._ceddp.close()
            self._ceddp = None
        for reader in self._readers:
            reader.close()
        for handle in self._handles:
            handle.undeclare()
        self._readers, self._handles = [], []


@contextlib.contextmanager
def discovering(transport: Transport, fleet: str) -> Iterator[Discovery]:
    """``Discovery`` as a context manager: closed on every exit path."""
    discovery = Discovery(transport, fleet)
    try:
        yield discovery
    finally:
        discovery.close()


def discover(transport: Transport, fleet: str, *, max_s: float = 3.0) -> FleetGraph:
    """The fleet's graph after watching it for at most ``max_s`` seconds (less when every
    present robot has announced and reported)."""
    with discovering(transport, fleet) as discovery:
        return discovery.settle(max_s=max_s)


__all__ = [
    "CEDDP",
    "CeddpStatsWatch",
    "Discovery",
    "Endpoint",
    "FleetGraph",
    "FleetObserver",
    "Node",
    "TopicEntry",
    "UnknownTopicError",
    "announced_keys",
    "describe_match_qos",
    "discover",
    "discovering",
    "inbound_rate",
    "match_qos_dict",
    "matches",
    "owner_of",
    "payload_type",
    "resolve",
    "topic_name",
    "watch_reports",
]


# ----------------------------------------------------------------------------- clock offsets


@dataclass(frozen=True)
class ClockOffset:
    """The CEDDP's clock minus a writer's (arpz/core/protocol/clock.py's sign: a stamp of that
    writer on the CEDDP's clock is ``stamp_ns + offset_ns``), and the round trip of the exchange it
    comes from (the offset is right within half of it)."""

    offset_ns: int
    delay_ns: int | None


def clock_offset(stats: RobotStats | None) -> ClockOffset | None:
    """The offset a robot reports in ``RobotStats.clock``, or None when it reports none (clock
    sync off, no reply yet, an older robot). The one place that reads it: ``topic delay`` and
    the doctor follow whatever this returns."""
    clock = stats.clock if stats is not None else None
    if clock is None or clock.offset_ns is None:
        return None
    return ClockOffset(clock.offset_ns, clock.delay_ns)
