"""A stand-in for a ROS 2 node running rmw_zenoh, for the bridge's tests (ROS 2 is not installed).

Written from rmw_zenoh's documentation (ros2/rmw_zenoh ``docs/design.md``: "Topic and Service
name mapping to Zenoh key expressions", "Graph Cache", "Publishers"), NOT from arpz.bridge: its
own token parser and key builder, CDR through ``rosbags``' Jazzy typestore directly
(arpz.core.rosmsg uses the Humble one), the attachment through Zenoh's own serializer
(``zenoh.ext``, which
rmw_zenoh's ``AttachmentData`` uses), and zenoh-python directly. Like a ROS 2 node it declares
its own node token and, for what it publishes, a publisher token, and computes the type hashes
of what it publishes itself.
"""

from __future__ import annotations

import dataclasses
import json
import threading
import time
from dataclasses import dataclass
from typing import Any

import zenoh
from rosbags.typesys import Stores, get_typestore
from zenoh.ext import Int64, UInt8, z_deserialize, z_serialize

STORE = get_typestore(Stores.ROS2_JAZZY)


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
        """``pkg::msg::dds_::Name_`` -> ``pkg/msg/Name``."""
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
