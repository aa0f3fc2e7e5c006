"""RIHS01 type hashes (REP 2016), computed from the message definitions.

A ROS 2 type hash is ``RIHS01_`` and the SHA-256 of a canonical JSON of the type's description
(its fields and every type they refer to, with rosidl's field type ids), as
``rosidl_generator_type_description`` writes it. rmw_zenoh puts the hash in every data key and
token, so a subscriber whose definition of a type differs never matches a publisher of it.

``rosbags``' typestore computes this hash from the definitions it carries
(``Typestore.hash_rihs01``); arpz.core.rosmsg already uses that typestore for the messages, so the
hash and the CDR come from one set of definitions. The golden tests check it against hashes
published by ROS 2 itself (tests/unit/bridge/test_type_hash.py).
"""

from __future__ import annotations

import functools
import hashlib
import json
import re
from typing import Any, Final

from arpz.core.errors import ArpzError
from arpz.core.msgtypes import FieldDef, MessageTypes
from arpz.core.rosmsg.convert import STORE

RIHS01: Final = re.compile(r"^RIHS01_[0-9a-f]{64}$")


class UnknownTypeError(ArpzError, KeyError):
    """A ROS 2 type whose definition arpz does not carry."""

    def __str__(self) -> str:
        return str(self.args[0])


@functools.lru_cache(maxsize=256)
def type_hash(ros_type: str) -> str:
    """``RIHS01_<64 hex digits>`` of ``ros_type`` (e.g. ``sensor_msgs/msg/LaserScan``)."""
    if ros_type not in STORE.fielddefs:
        raise UnknownTypeError(
            f"no message definition of {ros_type!r} (arpz knows the standard ROS 2 types of "
            "the rosbags typestore)"
        )
    digest = str(STORE.hash_rihs01(ros_type))
    if not RIHS01.match(digest):  # a typestore that changed its output format
        raise ValueError(f"type hash of {ros_type} is not RIHS01: {digest!r}")
    return digest


# -- services ----------------------------------------------------------------------------------

#: rosidl's field type ids (type_description_interfaces/msg/FieldType); a ``.msg`` ``char`` is a
#: uint8 and ``byte`` an octet in ROS 2 (rosidl_adapter), whatever a parser calls them
_TYPE_IDS: Final[dict[str, int]] = {
    "int8": 2,
    "uint8": 3,
    "char": 3,
    "int16": 4,
    "uint16": 5,
    "int32": 6,
    "uint32": 7,
    "int64": 8,
    "uint64": 9,
    "float32": 10,
    "float64": 11,
    "bool": 15,
    "byte": 16,
    "string": 17,
    "wstring": 18,
}
_NESTED: Final = 1
#: added to an element's id: a fixed array, a bounded sequence, an unbounded sequence
_ARRAY, _BOUNDED, _UNBOUNDED = 48, 96, 144
_PLACEHOLDER: Final = "structure_needs_at_least_one_member"
#: service_msgs/msg/ServiceEventInfo and what it refers to, as rosidl describes them (the event
#: message every service type carries since Iron)
_EVENT_INFO: Final = "service_msgs/msg/ServiceEventInfo"
_TIME: Final = "builtin_interfaces/msg/Time"


def _field(name: str, type_id: int, capacity: int = 0, nested: str = "") -> dict[str, Any]:
    return {
        "name": name,
        "type": {
            "type_id": type_id,
            "capacity": capacity,
            "string_capacity": 0,
            "nested_type_name": nested,
        },
    }


def _fields_of(field_defs: list[FieldDef]) -> list[dict[str, Any]]:
    fields = []
    for f in field_defs:
        element = _NESTED if f.message is not None else _TYPE_IDS[str(f.base)]
        if not f.sequence:
            fields.append(_field(f.name, element, nested=f.message or ""))
        elif f.fixed:
            fields.append(_field(f.name, element + _ARRAY, f.length, f.message or ""))
        elif f.length:
            fields.append(_field(f.name, element + _BOUNDED, f.length, f.message or ""))
        else:
            fields.append(_field(f.name, element + _UNBOUNDED, nested=f.message or ""))
    return fields or [_field(_PLACEHOLDER, _TYPE_IDS["uint8"])]


def service_type_hash(service: str, types: MessageTypes) -> str:
    """``RIHS01_<64 hex digits>`` of service type ``service`` (``std_srvs/srv/Trigger``): what
    rmw_zenoh puts in a service's key and its SS / SC tokens.

    REP 2016 hashes a service as a type of three fields, ``request_message``,
    ``response_message`` and ``event_message`` (``<service>_Event``: ``info``, a
    ``service_msgs/msg/ServiceEventInfo``, and at most one request and one response), with every
    type they refer to. Computed here from ``types``' definitions of the request and response
    (rosbags' typestore hashes messages only, and writes a ``char`` as ROS 2's ``char`` id where
    rosidl writes uint8). A bounded string's bound is not in ``MessageTypes``' field
    definitions: a request or response with one gets a hash ROS 2 does not, which rmw_zenoh's
    clients then do not match. Raises MessageTypeError for an unknown service."""
    request, response = types.service_types(service)
    event = f"{service}_Event"
    described: dict[str, list[dict[str, Any]]] = {
        service: [
            _field("request_message", _NESTED, nested=request),
            _field("response_message", _NESTED, nested=response),
            _field("event_message", _NESTED, nested=event),
        ],
        event: [
            _field("info", _NESTED, nested=_EVENT_INFO),
            _field("request", _NESTED + _BOUNDED, 1, request),
            _field("response", _NESTED + _BOUNDED, 1, response),
        ],
        _EVENT_INFO: [
            _field("event_type", _TYPE_IDS["uint8"]),
            _field("stamp", _NESTED, nested=_TIME),
            _field("client_gid", _TYPE_IDS["uint8"] + _ARRAY, 16),
            _field("sequence_number", _TYPE_IDS["int64"]),
        ],
        _TIME: [_field("sec", _TYPE_IDS["int32"]), _field("nanosec", _TYPE_IDS["uint32"])],
    }
    pending = [request, response]
    while pending:
        name = pending.pop()
        if name in described:
            continue
        field_defs = types.field_defs(name)
        described[name] = _fields_of(field_defs)
        pending += [f.message for f in field_defs if f.message is not None]
    description = {
        "type_description": {"type_name": service, "fields": described[service]},
        "referenced_type_descriptions": [
            {"type_name": name, "fields": described[name]}
            for name in sorted(described)
            if name != service
        ],
    }
    return "RIHS01_" + hashlib.sha256(json.dumps(description).encode()).hexdigest()
