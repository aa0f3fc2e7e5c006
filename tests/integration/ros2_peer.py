"""A stand-in for a ROS 2 node running rmw_zenoh, for the bridge's tests (rmw_zenoh is not
installed).

Written from rmw_zenoh's documentation (ros2/rmw_zenoh ``docs/design.md``: "Topic and Service
name mapping to Zenoh key expressions", "Graph Cache", "Publishers", "Service Clients"), NOT
from arpz.bridge: its own token parser and key builder, CDR through ``rosbags``' Jazzy typestore
directly (arpz.core.rosmsg uses the Humble one), the attachment through Zenoh's own serializer
(``zenoh.ext``, which rmw_zenoh's ``AttachmentData`` uses), and zenoh-python directly. Like a
ROS 2 node it declares its own node token and, for what it publishes, a publisher token, and
computes the type hashes of what it publishes itself. Its service client (``call``) declares an
SC token and sends a ``get`` on the service's key with the request's attachment (sequence
number, timestamp, its GID), target ALL_COMPLETE, as design.md's "Service Clients" says; the
service type hashes are those ROS 2's rosidl wrote (``SERVICE_HASHES``).
"""

from __future__ import annotations

import dataclasses
import json
import threading
import time
from dataclasses import dataclass
from typing import Any

import zenoh
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from zenoh.ext import Int64, UInt8, z_deserialize, z_serialize

STORE = get_typestore(Stores.ROS2_JAZZY)
# the request and response messages of std_srvs/srv/Trigger, registered under the service's
# names (rosbags parses message names only, package/msg/Name); an empty structure holds the one
# uint8 ROS 2 gives it
STORE.register(
    {
        f"std_srvs/srv/Trigger_{half}": get_types_from_msg(text, f"std_srvs/msg/Trigger_{half}")[
            f"std_srvs/msg/Trigger_{half}"
        ]
        for half, text in (
            ("Request", "uint8 structure_needs_at_least_one_member"),
            ("Response", "bool success\nstring message"),
        )
    }
)
#: service type hashes as ROS 2 computes them (REP 2016: request, response and event message):
#: rosidl's own output, ``share/std_srvs/srv/Trigger.json`` of the ros-std-srvs 5.5.1 wheel
SERVICE_HASHES = {
    "std_srvs/srv/Trigger": (
        "RIHS01_eeff2cd6fa5ad9d27cdf4dec64818317839b62f212a91e6b5304b634b2062c5f"
    ),
}


@dataclass(frozen=True)
class PeerEntity:
    """What one liveliness token says (design.md "Graph Cache")."""

    token: str
    domain: int
    zid: str
    kind: str
    namespace: str
    node: str
    topic: str = ""
    dds_type: str = ""
    type_hash: str = ""
    qos: str = ""

    @property
    def ros_type(self) -> str:
        """``pkg::msg::dds_::Name_`` -> ``pkg/msg/Name`` (``pkg/srv/Name`` for a service)."""
        pkg, sub, _, name = self.dds_type.split("::")
        return f"{pkg}/{sub}/{name.rstrip('_')}"

    @property
    def data_key(self) -> str:
        """design.md: ``<domain_id>/<fully_qualified_name>/<type_name>/<type_hash>``."""
        return f"{self.domain}/{self.topic.strip('/')}/{self.dds_type}/{self.type_hash}"


def parse(token: str) -> PeerEntity:
    chunks = token.split("/")
    assert chunks[0] == "@ros2_lv", token
    unmangle = {c: chunks[c].replace("%", "/") for c in range(len(chunks))}
    entity = PeerEntity(
        token=token,
        domain=int(chunks[1]),
        zid=chunks[2],
        kind=chunks[5],
        namespace=unmangle[7],
        node=unmangle[8],
    )
    if entity.kind == "NN":
        assert len(chunks) == 9, token
        return entity
    assert len(chunks) == 13, token
    return dataclasses.replace(
        entity, topic=unmangle[9], dds_type=chunks[10], type_hash=chunks[11], qos=chunks[12]
    )


def qos_fields(text: str) -> dict[str, str]:
    """The token's QoS chunk (liveliness_utils.cpp ``qos_to_keyexpr``): empty = default."""
    reliability, durability, history, deadline, lifespan, liveliness = text.split(":")
    kind, depth = history.split(",")
    return {
        "reliability": reliability,
        "durability": durability,
        "history": kind,
        "depth": depth,
        "deadline": deadline,
        "lifespan": lifespan,
        "liveliness": liveliness,
    }


@dataclass
class Received:
    key: str
    message: Any
    sequence_number: int
    source_timestamp_ns: int
    gid: bytes
    arrival_ns: int


@dataclass
class Reply:
    """A service's response (None: the query ended without one) and its reply attachment."""

    key: str
    response: Any
    sequence_number: int
    source_timestamp_ns: int
    gid: bytes


#: this peer's GID, as a client's request header carries it
GID = bytes(range(100, 116))


class Ros2Peer:
    """One ROS 2 "node" on a Zenoh client session."""

    def __init__(self, endpoint: str, *, domain: int = 0, node: str = "peer") -> None:
        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps("client"))
        conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        self.session = zenoh.open(conf)
        self.domain = domain
        self.zid = str(self.session.zid())
        self._lock = threading.Lock()
        self._tokens: set[str] = set()
        self.received: dict[str, list[Received]] = {}
        self._declared: list[Any] = []
        self._next_id = 1
        self._seq: dict[str, int] = {}
        self._graph = self.session.liveliness().declare_subscriber(
            f"@ros2_lv/{domain}/**", self._on_token, history=True
        )
        self._declared.append(
            self.session.liveliness().declare_token(
                f"@ros2_lv/{domain}/{self.zid}/0/0/NN/%/%/{node}"
            )
        )
        self.node = node

    def _on_token(self, sample: zenoh.Sample) -> None:
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._tokens.add(str(sample.key_expr))
            else:
                self._tokens.discard(str(sample.key_expr))

    def graph(self) -> list[PeerEntity]:
        with self._lock:
            tokens = sorted(self._tokens)
        return [parse(t) for t in tokens]

    def find(self, kind: str, topic: str) -> PeerEntity | None:
        for entity in self.graph():
            if entity.kind == kind and entity.topic == topic:
                return entity
        return None

    # -- subscribing -------------------------------------------------------------------------------

    def subscribe(self, publisher: PeerEntity) -> None:
        """Receive what ``publisher``'s topic carries, decoded with rosbags."""
        ros_type = publisher.ros_type
        topic = publisher.topic

        def on_sample(sample: zenoh.Sample) -> None:
            arrival = time.time_ns()
            attachment = sample.attachment
            assert attachment is not None, "rmw_zenoh samples carry an attachment"
            seq, stamp, gid = z_deserialize(tuple[Int64, Int64, list[UInt8]], attachment)
            message = STORE.deserialize_cdr(sample.payload.to_bytes(), ros_type)
            item = Received(str(sample.key_expr), message, seq, stamp, bytes(gid), arrival)
            with self._lock:
                self.received.setdefault(topic, []).append(item)

        self._declared.append(self.session.declare_subscriber(publisher.data_key, on_sample))

    def messages(self, topic: str) -> list[Received]:
        with self._lock:
            return list(self.received.get(topic, []))

    # -- publishing --------------------------------------------------------------------------------

    def publisher(self, topic: str, ros_type: str, *, depth: int = 10) -> str:
        """Declare a publisher token and return the data key, as rmw_zenoh does for a
        ``create_publisher`` (the hash computed here, from rosbags' definitions)."""
        pkg, sub, name = ros_type.split("/")
        dds = f"{pkg}::{sub}::dds_::{name}_"
        type_hash = STORE.hash_rihs01(ros_type)
        entity_id, self._next_id = self._next_id, self._next_id + 1
        mangled = topic.replace("/", "%")
        token = (
            f"@ros2_lv/{self.domain}/{self.zid}/0/{entity_id}/MP/%/%/{self.node}/{mangled}/"
            f"{dds}/{type_hash}/::,{depth}:,:,:,,"
        )
        self._declared.append(self.session.liveliness().declare_token(token))
        return f"{self.domain}/{topic.strip('/')}/{dds}/{type_hash}"

    def publish(self, key: str, ros_type: str, message: Any) -> None:
        seq = self._seq.get(key, 0) + 1
        self._seq[key] = seq
        gid = [UInt8(b) for b in range(16)]
        attachment = z_serialize((Int64(seq), Int64(time.time_ns()), gid))
        payload = bytes(STORE.serialize_cdr(message, ros_type, little_endian=True))
        self.session.put(key, payload, attachment=attachment)

    # -- calling a service ---------------------------------------------------------------------

    def client(self, service: str, srv_type: str) -> str:
        """Declare a service client's SC token (design.md "Graph Cache": the service's mangled
        name, its DDS type name ``pkg::srv::dds_::Name_`` and type hash, the services' default
        QoS: RELIABLE, VOLATILE, KEEP_LAST 10) and return the service's key."""
        pkg, sub, name = srv_type.split("/")
        dds = f"{pkg}::{sub}::dds_::{name}_"
        type_hash = SERVICE_HASHES[srv_type]
        entity_id, self._next_id = self._next_id, self._next_id + 1
        token = (
            f"@ros2_lv/{self.domain}/{self.zid}/0/{entity_id}/SC/%/%/{self.node}/"
            f"{service.replace('/', '%')}/{dds}/{type_hash}/::,10:,:,:,,"
        )
        self._declared.append(self.session.liveliness().declare_token(token))
        return f"{self.domain}/{service.strip('/')}/{dds}/{type_hash}"

    def call(self, key: str, srv_type: str, request: Any, timeout_s: float = 10.0) -> Reply:
        """design.md "Service Clients": ``get`` on the service's key with the serialized request
        and the attachment (sequence number, source timestamp, client GID), target
        ALL_COMPLETE; the response comes back as a reply whose attachment carries the same
        sequence number and client GID."""
        seq = self._seq.get(key, 0) + 1
        self._seq[key] = seq
        attachment = z_serialize((Int64(seq), Int64(time.time_ns()), [UInt8(b) for b in GID]))
        payload = bytes(STORE.serialize_cdr(request, f"{srv_type}_Request", little_endian=True))
        replies = self.session.get(
            key,
            payload=payload,
            attachment=attachment,
            target=zenoh.QueryTarget.ALL_COMPLETE,
            timeout=timeout_s,
        )
        got: list[Reply] = []
        for reply in replies:
            ok = reply.ok
            if ok is None:
                continue
            assert ok.attachment is not None, "rmw_zenoh replies carry an attachment"
            r_seq, r_stamp, r_gid = z_deserialize(tuple[Int64, Int64, list[UInt8]], ok.attachment)
            response = STORE.deserialize_cdr(ok.payload.to_bytes(), f"{srv_type}_Response")
            got.append(Reply(str(ok.key_expr), response, r_seq, r_stamp, bytes(r_gid)))
        assert len(got) <= 1, f"one server answers, got {len(got)} replies"
        return got[0] if got else Reply("", None, seq, 0, b"")

    def twist(self, v: float, omega: float) -> Any:
        vector = STORE.types["geometry_msgs/msg/Vector3"]
        return STORE.types["geometry_msgs/msg/Twist"](
            linear=vector(x=v, y=0.0, z=0.0), angular=vector(x=0.0, y=0.0, z=omega)
        )

    def close(self) -> None:
        for item in reversed(self._declared):
            item.undeclare()
        self._graph.undeclare()
        self.session.close()  # type: ignore[no-untyped-call]

    def __enter__(self) -> Ros2Peer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
