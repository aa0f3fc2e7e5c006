"""rmw_zenoh's wire protocol, as values: key expressions, liveliness tokens, QoS, attachments.

Everything here is pure (no Zenoh, no I/O), so the byte layouts are tested against the examples
of rmw_zenoh's own documentation (tests/unit/bridge/test_rmw_zenoh.py names each source). The
layouts, from ros2/rmw_zenoh ``docs/design.md`` and ``rmw_zenoh_cpp/src/detail/
liveliness_utils.cpp`` / ``attachment_helpers.cpp`` / ``qos.cpp`` (rmw_zenoh 0.2+, Jazzy and
Rolling, on Zenoh 1.x):

- data: ``<domain_id>/<topic without leading '/'>/<DDS type name>/<RIHS01 type hash>``, e.g.
  ``0/robot1/scan/sensor_msgs::msg::dds_::LaserScan_/RIHS01_64c1...``;
- graph: one liveliness token per entity, ``@ros2_lv/<domain_id>/<session zid>/<node id>/
  <entity id>/<NN|MP|MS|SS|SC>/<enclave>/<namespace>/<node>`` and, for publishers and
  subscriptions, ``/<topic>/<DDS type>/<type hash>/<qos>``, with '/' in names written '%';
- QoS in the token: ``R:D:H,depth:Ds,Dns:Ls,Lns:L,LLs,LLns`` where a field equal to rmw_zenoh's
  default is left empty (defaults: RELIABLE, VOLATILE, KEEP_LAST 42, infinite deadline, lifespan
  and lease, AUTOMATIC liveliness);
- attachment of every sample: sequence number (int64 LE), source timestamp (int64 LE, ns since
  the epoch), then the 16-byte GID as Zenoh's serializer writes an array (length 16 as one LEB128
  byte, then the bytes): 33 bytes;
- services: the key is a topic's with the service's DDS type (``std_srvs::srv::dds_::Trigger_``)
  and type hash (``type_hash.service_type_hash``), served by a complete queryable with an SS
  token (a client's is SC); a request is a ``get`` whose attachment is the request header (the
  33 bytes above, with the client's GID), and the reply's attachment carries the request's
  sequence number and client GID back with the reply's timestamp (design.md "Service Clients",
  "Service Servers").

The GID is rmw_zenoh's: XXH3-128 of the entity's token, its low 64 bits then its high 64 bits,
each little-endian (``Entity`` in rmw_zenoh's liveliness_utils.cpp). A ROS 2 node computes the
GID it shows for a remote entity from the token, so the ``publisher_gid`` in a received
message's info and the GID ``ros2 topic info -v`` shows for the bridge's publisher are the same
16 bytes, as tools that match the two expect (docs/ros2.md).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Final, NamedTuple

import xxhash

from arpz.core.errors import ArpzError
from arpz.core.protocol.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    LivelinessPolicy,
    QosProfile,
    ReliabilityPolicy,
)

ADMIN_SPACE: Final = "@ros2_lv"
NODE: Final = "NN"
PUBLISHER: Final = "MP"
SUBSCRIPTION: Final = "MS"
SERVICE: Final = "SS"
CLIENT: Final = "SC"
ENTITY_KINDS: Final = (NODE, PUBLISHER, SUBSCRIPTION, SERVICE, CLIENT)
#: rmw_zenoh writes '/' in names as this (a Zenoh key chunk holds no '/')
SLASH: Final = "%"
GID_BYTES: Final = 16

# rmw/types.h enumerations (the numbers the token carries)
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2
AUTOMATIC, MANUAL_BY_TOPIC = 1, 3
#: RMW_DURATION_INFINITE: (sec, nsec)
INFINITE: Final = (9_223_372_036, 999_999_999)


class WireError(ArpzError, ValueError):
    """Bytes or a key that are not what rmw_zenoh writes; the message says what is wrong."""


# -- names and types ---------------------------------------------------------------------------


def mangle(name: str) -> str:
    return name.replace("/", SLASH)


def demangle(name: str) -> str:
    return name.replace(SLASH, "/")


def dds_type_name(ros_type: str) -> str:
    """``sensor_msgs/msg/LaserScan`` -> ``sensor_msgs::msg::dds_::LaserScan_`` (the CDR type name
    rmw_zenoh puts in keys and tokens)."""
    parts = ros_type.split("/")
    if len(parts) != 3 or not all(parts):
        raise WireError(f"{ros_type!r} is not a ROS 2 type name such as 'std_msgs/msg/String'")
    package, sub, name = parts
    return f"{package}::{sub}::dds_::{name}_"


def ros_type_name(dds_type: str) -> str:
    """The inverse of ``dds_type_name``."""
    parts = dds_type.split("::")
    if len(parts) != 4 or parts[2] != "dds_" or not parts[3].endswith("_") or len(parts[3]) < 2:
        raise WireError(
            f"{dds_type!r} is not a DDS type name such as 'std_msgs::msg::dds_::String_'"
        )
    return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"


def topic_key(domain_id: int, topic: str, ros_type: str, type_hash: str) -> str:
    """The key expression a ROS 2 topic's samples travel on."""
    return f"{domain_id}/{topic.strip('/')}/{dds_type_name(ros_type)}/{type_hash}"


class TopicKey(NamedTuple):
    domain_id: int
    topic: str
    ros_type: str
    type_hash: str


def parse_topic_key(key: str) -> TopicKey | None:
    """A data key split into its parts (the topic with its leading '/'); None if it is not one."""
    parts = key.split("/")
    if len(parts) < 4 or not parts[0].isdigit():
        return None
    try:
        ros_type = ros_type_name(parts[-2])
    except WireError:
        return None
    if not parts[-1].startswith("RIHS01_"):
        return None
    return TopicKey(int(parts[0]), "/" + "/".join(parts[1:-2]), ros_type, parts[-1])


# -- QoS ---------------------------------------------------------------------------------------


def _duration(seconds: float) -> tuple[int, int]:
    """arpz's "0 = none" seconds as an rmw duration (infinite for 0)."""
    if seconds <= 0:
        return INFINITE
    ns = round(seconds * 1e9)
    return ns // 1_000_000_000, ns % 1_000_000_000


@dataclass(frozen=True)
class RmwQos:
    """A QoS profile as rmw_zenoh's token carries it (rmw/types.h numbers)."""

    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST
    depth: int = 42
    deadline: tuple[int, int] = INFINITE
    lifespan: tuple[int, int] = INFINITE
    liveliness: int = AUTOMATIC
    lease: tuple[int, int] = INFINITE

    def encode(self) -> str:
        """``qos_to_keyexpr``: each field equal to rmw_zenoh's default is left empty."""
        d = DEFAULT_QOS

        def f(value: int, default: int) -> str:
            return "" if value == default else str(value)

        return (
            f"{f(self.reliability, d.reliability)}:{f(self.durability, d.durability)}:"
            f"{f(self.history, d.history)},{f(self.depth, d.depth)}:"
            f"{f(self.deadline[0], d.deadline[0])},{f(self.deadline[1], d.deadline[1])}:"
            f"{f(self.lifespan[0], d.lifespan[0])},{f(self.lifespan[1], d.lifespan[1])}:"
            f"{f(self.liveliness, d.liveliness)},{f(self.lease[0], d.lease[0])},"
            f"{f(self.lease[1], d.lease[1])}"
        )

    @classmethod
    def decode(cls, text: str) -> RmwQos:
        """``keyexpr_to_qos``: raises WireError for a malformed QoS chunk."""
        parts = text.split(":")
        if len(parts) != 6:
            raise WireError(f"QoS {text!r} has {len(parts)} ':'-separated fields, not 6")
        history, deadline, lifespan, liveliness = (p.split(",") for p in parts[2:])
        if (len(history), len(deadline), len(lifespan), len(liveliness)) != (2, 2, 2, 3):
            raise WireError(f"QoS {text!r} does not have the fields H,depth:s,ns:s,ns:L,s,ns")
        d = DEFAULT_QOS

        def n(value: str, default: int) -> int:
            if not value:
                return default
            if not value.isdigit():
                raise WireError(f"QoS {text!r}: {value!r} is not a number")
            return int(value)

        return cls(
            reliability=n(parts[0], d.reliability),
            durability=n(parts[1], d.durability),
            history=n(history[0], d.history),
            depth=n(history[1], d.depth),
            deadline=(n(deadline[0], d.deadline[0]), n(deadline[1], d.deadline[1])),
            lifespan=(n(lifespan[0], d.lifespan[0]), n(lifespan[1], d.lifespan[1])),
            liveliness=n(liveliness[0], d.liveliness),
            lease=(n(liveliness[1], d.lease[0]), n(liveliness[2], d.lease[1])),
        )

    def describe(self) -> str:
        """As ``ros2 topic info -v`` words it, on one line."""
        reliability = {RELIABLE: "RELIABLE", BEST_EFFORT: "BEST_EFFORT"}
        durability = {VOLATILE: "VOLATILE", TRANSIENT_LOCAL: "TRANSIENT_LOCAL"}
        history = f"KEEP_LAST ({self.depth})" if self.history == KEEP_LAST else "KEEP_ALL"

        def duration(value: tuple[int, int]) -> str:
            return "Infinite" if value == INFINITE else f"{value[0] + value[1] / 1e9:g} s"

        return (
            f"{reliability.get(self.reliability, str(self.reliability))}, "
            f"{durability.get(self.durability, str(self.durability))}, {history}, "
            f"deadline {duration(self.deadline)}, lifespan {duration(self.lifespan)}"
        )


#: rmw_zenoh_cpp/src/detail/qos.cpp
DEFAULT_QOS: Final = RmwQos()


#: the QoS of a service server and client (rmw's ``rmw_qos_profile_services_default``)
SERVICE_QOS: Final = RmwQos(depth=10)


def qos_from_profile(profile: QosProfile | None, *, transient_local: bool = False) -> RmwQos:
    """The ROS 2 QoS a bridged topic offers for an arpz profile (None: arpz's plain mode).

    Durability is VOLATILE unless ``transient_local`` (the rclpy backend: its RMW keeps the
    publisher's history for late joiners) and the profile asks for TRANSIENT_LOCAL: the
    rmw_zenoh backend keeps no publication cache (rmw_zenoh serves TRANSIENT_LOCAL from an
    AdvancedPublisher's cache), so it does not claim one. Plain mode offers BEST_EFFORT:
    nothing is recovered end to end before the bridge."""
    if profile is None:
        return RmwQos(reliability=BEST_EFFORT, depth=1)
    keeps = transient_local and profile.durability is DurabilityPolicy.TRANSIENT_LOCAL
    return RmwQos(
        reliability=RELIABLE if profile.reliability is ReliabilityPolicy.RELIABLE else BEST_EFFORT,
        durability=TRANSIENT_LOCAL if keeps else VOLATILE,
        history=KEEP_LAST if profile.history is HistoryPolicy.KEEP_LAST else KEEP_ALL,
        depth=profile.depth if profile.history is HistoryPolicy.KEEP_LAST else DEFAULT_QOS.depth,
        deadline=_duration(profile.deadline_s),
        lifespan=_duration(profile.lifespan_s),
        liveliness=(
            AUTOMATIC if profile.liveliness is LivelinessPolicy.AUTOMATIC else MANUAL_BY_TOPIC
        ),
        lease=_duration(profile.lease_duration_s),
    )


# -- liveliness tokens -------------------------------------------------------------------------


@dataclass(frozen=True)
class Entity:
    """One entity of the ROS 2 graph, as its liveliness token names it. ``namespace`` and
    ``topic`` are plain ROS names ("/" for the root namespace); ``topic`` is empty for a node."""

    domain_id: int
    zid: str
    node_id: str
    entity_id: str
    kind: str
    namespace: str
    node: str
    enclave: str = "/"
    topic: str = ""
    ros_type: str = ""
    type_hash: str = ""
    qos: RmwQos | None = None

    def token(self) -> str:
        """The liveliness token's key expression."""
        chunks = [
            ADMIN_SPACE,
            str(self.domain_id),
            self.zid,
            self.node_id,
            self.entity_id,
            self.kind,
            mangle(self.enclave),
            mangle(self.namespace),
            mangle(self.node),
        ]
        if self.kind != NODE:
            if self.qos is None:
                raise WireError(f"a {self.kind} token needs a topic, a type and a QoS")
            chunks += [
                mangle(self.topic),
                dds_type_name(self.ros_type),
                self.type_hash,
                self.qos.encode(),
            ]
        return "/".join(chunks)

    @property
    def gid(self) -> bytes:
        """16 bytes naming this entity, derived as rmw_zenoh derives it (the module's docstring)."""
        return gid_of_token(self.token())

    @property
    def data_key(self) -> str:
        return topic_key(self.domain_id, self.topic, self.ros_type, self.type_hash)


def token_expr(domain_id: int) -> str:
    """The key expression that matches every entity token of a domain (``liveliness get`` or a
    liveliness subscriber on it gives the whole ROS 2 graph)."""
    return f"{ADMIN_SPACE}/{domain_id}/**"


def parse_token(key: str) -> Entity:
    """An entity from its liveliness token (``Entity::make(keyexpr)``); raises WireError."""
    parts = key.split("/")
    if len(parts) < 9 or parts[0] != ADMIN_SPACE:
        raise WireError(f"{key!r} is not an rmw_zenoh liveliness token ({ADMIN_SPACE}/...)")
    if any(not p for p in parts):
        raise WireError(f"liveliness token {key!r} has an empty chunk")
    if not parts[1].isdigit():
        raise WireError(f"liveliness token {key!r}: domain id {parts[1]!r} is not a number")
    kind = parts[5]
    if kind not in ENTITY_KINDS:
        raise WireError(f"liveliness token {key!r}: unknown entity kind {kind!r}")
    base = {
        "domain_id": int(parts[1]),
        "zid": parts[2],
        "node_id": parts[3],
        "entity_id": parts[4],
        "kind": kind,
        "enclave": demangle(parts[6]),
        "namespace": demangle(parts[7]),
        "node": demangle(parts[8]),
    }
    if kind == NODE:
        if len(parts) != 9:
            raise WireError(f"node token {key!r} has {len(parts)} chunks, not 9")
        return Entity(**base)  # type: ignore[arg-type]
    if len(parts) != 13:
        raise WireError(f"{kind} token {key!r} has {len(parts)} chunks, not 13")
    return Entity(
        **base,  # type: ignore[arg-type]
        topic=demangle(parts[9]),
        ros_type=ros_type_name(parts[10]),
        type_hash=parts[11],
        qos=RmwQos.decode(parts[12]),
    )


class GraphRecord(NamedTuple):
    """One publisher or subscription of the ROS 2 graph, for ``arpz topic list``."""

    node: str
    topic: str
    ros_type: str
    role: str
    qos: RmwQos


def graph_records(tokens: list[str]) -> tuple[list[GraphRecord], int]:
    """The publishers and subscriptions among rmw_zenoh liveliness tokens (nodes, services and
    clients are skipped), and how many tokens were not rmw_zenoh's (counted, not raised): what
    ``python -m arpz topic list`` shows for the ROS 2 side (docs/ros2.md)."""
    records: list[GraphRecord] = []
    bad = 0
    for key in tokens:
        try:
            entity = parse_token(key)
        except WireError:
            bad += 1
            continue
        if entity.kind not in (PUBLISHER, SUBSCRIPTION) or entity.qos is None:
            continue
        node = entity.namespace.rstrip("/") + "/" + entity.node
        role = "publisher" if entity.kind == PUBLISHER else "subscription"
        records.append(GraphRecord(node, entity.topic, entity.ros_type, role, entity.qos))
    return records, bad


# -- attachment --------------------------------------------------------------------------------

_ATTACHMENT = struct.Struct("<qqB16s")
ATTACHMENT_BYTES: Final = _ATTACHMENT.size


class Attachment(NamedTuple):
    sequence_number: int
    source_timestamp_ns: int
    gid: bytes


def gid_of_token(token: str) -> bytes:
    """rmw_zenoh's GID of the entity whose liveliness token is ``token``: XXH3-128, low half
    first, each half little-endian (memcpy of the two uint64 on the little-endian hosts ROS 2
    runs on)."""
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(GID_BYTES, "little")


def attachment(sequence_number: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """The 33 bytes rmw_zenoh attaches to every sample (``AttachmentData::serialize_to_zbytes``)."""
    if len(gid) != GID_BYTES:
        raise WireError(f"a GID is {GID_BYTES} bytes, got {len(gid)}")
    return _ATTACHMENT.pack(sequence_number, source_timestamp_ns, GID_BYTES, gid)


def parse_attachment(data: bytes) -> Attachment:
    if len(data) != ATTACHMENT_BYTES:
        raise WireError(f"an rmw_zenoh attachment is {ATTACHMENT_BYTES} bytes, got {len(data)}")
    seq, stamp, length, gid = _ATTACHMENT.unpack(data)
    if length != GID_BYTES:
        raise WireError(f"attachment GID length {length}, expected {GID_BYTES}")
    return Attachment(seq, stamp, gid)
