"""Event payloads (mirroring the ROS 2 status fields) and the callback containers.

Callbacks run on the channel's worker thread, never on a Zenoh thread, so they may block briefly
or call back into the channel; a slow callback delays the channel, it never loses a sample
(reliable readers recover what their queue dropped).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import msgspec

from arpz.core.protocol.qos import QosPolicyKind


class DataInfo(msgspec.Struct, frozen=True, gc=False):
    """Where a delivered payload came from: ``key`` is the concrete topic key (useful with a
    wildcard reader), ``writer`` the writer's guid in hex (a new one per writer incarnation)."""

    key: str
    writer: str
    seq: int
    stamp_ns: int
    retransmitted: bool = False


class DeadlineMissedStatus(msgspec.Struct, frozen=True):
    """Offered (writer) or requested (reader) deadline missed; one count per missed period."""

    total_count: int
    total_count_change: int
    #: the writer concerned, on the reader side ("" on the writer side)
    writer: str = ""


class LivelinessLostStatus(msgspec.Struct, frozen=True):
    """A MANUAL_BY_TOPIC writer did not assert its liveliness within its lease."""

    total_count: int
    total_count_change: int


class LivelinessChangedStatus(msgspec.Struct, frozen=True):
    alive_count: int
    not_alive_count: int
    alive_count_change: int
    not_alive_count_change: int
    writer: str = ""


class MessageLostStatus(msgspec.Struct, frozen=True):
    """Samples irrecoverably lost: overwritten in a KEEP_LAST history before being acknowledged,
    declared lost by a GAP or after the reorder timeout, or gaps seen by a BEST_EFFORT reader."""

    total_count: int
    total_count_change: int
    writer: str = ""


class IncompatibleQosStatus(msgspec.Struct, frozen=True):
    total_count: int
    total_count_change: int
    last_policy_kind: QosPolicyKind
    #: guid of the peer that could not be matched
    peer: str = ""


class MatchedStatus(msgspec.Struct, frozen=True):
    total_count: int
    total_count_change: int
    current_count: int
    current_count_change: int
    peer: str = ""


@dataclass(frozen=True, kw_only=True)
class WriterEventCallbacks:
    deadline: Callable[[DeadlineMissedStatus], None] | None = None
    liveliness: Callable[[LivelinessLostStatus], None] | None = None
    incompatible_qos: Callable[[IncompatibleQosStatus], None] | None = None
    matched: Callable[[MatchedStatus], None] | None = None
    #: a reader asked for samples KEEP_LAST had already overwritten (they were answered by GAP)
    message_lost: Callable[[MessageLostStatus], None] | None = None


class UnchangedStatus(msgspec.Struct, frozen=True):
    """A writer proved its topic alive and its last value current without resending it (the
    robot's local cache held a repeat back): for planners that judge data by its age. arpz
    addition, no ROS 2 equivalent."""

    total_count: int
    key: str
    writer: str
    stamp_ns: int


@dataclass(frozen=True, kw_only=True)
class ReaderEventCallbacks:
    deadline: Callable[[DeadlineMissedStatus], None] | None = None
    liveliness: Callable[[LivelinessChangedStatus], None] | None = None
    message_lost: Callable[[MessageLostStatus], None] | None = None
    incompatible_qos: Callable[[IncompatibleQosStatus], None] | None = None
    matched: Callable[[MatchedStatus], None] | None = None
    unchanged: Callable[[UnchangedStatus], None] | None = None
