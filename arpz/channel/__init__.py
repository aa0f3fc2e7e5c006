"""An end-to-end reliable channel with ROS 2 QoS semantics over Zenoh (docs/reliability.md).

Zenoh's RELIABLE retransmits nothing end to end; this package adds what RTPS adds under DDS:
per-writer sequence numbers, heartbeats, ACKNACK/GAP, KEEP_LAST/KEEP_ALL histories, durability,
deadline, lifespan and liveliness, matching with incompatible-QoS events, and the invariant that
for every reader delivered + reported lost == sent during the match. ``FrameWriter`` and
``FrameReader`` carry large samples (camera frames) as fragments of one radio frame each.
"""

from arpz.channel.large import (
    QOS_FRAMES_ALL,
    QOS_VIDEO,
    FrameInfo,
    FrameReader,
    FrameReaderStats,
    FrameWriter,
    FrameWriterStats,
)
from arpz.channel.reader import Reader
from arpz.channel.writer import Writer
from arpz.core.protocol._common import AWAY_RETENTION_S
from arpz.core.protocol.events import (
    DataInfo,
    DeadlineMissedStatus,
    IncompatibleQosStatus,
    LivelinessChangedStatus,
    LivelinessLostStatus,
    MatchedStatus,
    MessageLostStatus,
    ReaderEventCallbacks,
    UnchangedStatus,
    WriterEventCallbacks,
)
from arpz.core.protocol.qos import (
    QOS_DEFAULT,
    QOS_LATCHED,
    QOS_PARAMETERS,
    QOS_RELIABLE_ALL,
    QOS_SENSOR_DATA,
    DurabilityPolicy,
    HistoryPolicy,
    LivelinessPolicy,
    QosPolicyKind,
    QosProfile,
    ReliabilityPolicy,
    incompatible_policy,
    load_qos,
    qos_from_toml,
)
from arpz.core.protocol.reader_machine import PLAIN_PEER, ReaderMachine, ReaderStats
from arpz.core.protocol.timers import Clock, FakeClock, SystemClock
from arpz.core.protocol.writer_machine import HistoryFullError, WriterMachine, WriterStats

__all__ = [
    "AWAY_RETENTION_S",
    "PLAIN_PEER",
    "QOS_DEFAULT",
    "QOS_FRAMES_ALL",
    "QOS_LATCHED",
    "QOS_PARAMETERS",
    "QOS_RELIABLE_ALL",
    "QOS_SENSOR_DATA",
    "QOS_VIDEO",
    "Clock",
    "DataInfo",
    "DeadlineMissedStatus",
    "DurabilityPolicy",
    "FakeClock",
    "FrameInfo",
    "FrameReader",
    "FrameReaderStats",
    "FrameWriter",
    "FrameWriterStats",
    "HistoryFullError",
    "HistoryPolicy",
    "IncompatibleQosStatus",
    "LivelinessChangedStatus",
    "LivelinessLostStatus",
    "LivelinessPolicy",
    "MatchedStatus",
    "MessageLostStatus",
    "QosPolicyKind",
    "QosProfile",
    "Reader",
    "ReaderEventCallbacks",
    "ReaderMachine",
    "ReaderStats",
    "ReliabilityPolicy",
    "SystemClock",
    "UnchangedStatus",
    "Writer",
    "WriterEventCallbacks",
    "WriterMachine",
    "WriterStats",
    "incompatible_policy",
    "load_qos",
    "qos_from_toml",
]
