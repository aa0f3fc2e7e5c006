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
import re
from typing import Final

from arpz.core.errors import ArpzError
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
