"""QoS policies with ROS 2 semantics, their compatibility rules and their compact key encoding.

A profile is a frozen msgspec Struct so that the same type is the Python API, the TOML file
format (``forbid_unknown_fields`` turns a typo into an error naming the field) and the value
compared during matching. Durations are float seconds and ``0.0`` means infinite, as in ROS 2.
"""

from __future__ import annotations

import enum
import math
import re
from pathlib import Path
from typing import Final

import msgspec

from arpz.core.errors import ArpzError
from arpz.core.protocol.wire import MAX_BATCH

#: the longest an adaptive heartbeat period grows, in periods (``heartbeat_backoff``)
MAX_HEARTBEAT_BACKOFF: Final = 64


class QosError(ArpzError, ValueError):
    """A QoS profile that cannot be used; the message names the field."""


class ReliabilityPolicy(enum.Enum):
    BEST_EFFORT = "best_effort"
    RELIABLE = "reliable"


class HistoryPolicy(enum.Enum):
    KEEP_LAST = "keep_last"
    KEEP_ALL = "keep_all"


class DurabilityPolicy(enum.Enum):
    VOLATILE = "volatile"
    TRANSIENT_LOCAL = "transient_local"


class LivelinessPolicy(enum.Enum):
    AUTOMATIC = "automatic"
    MANUAL_BY_TOPIC = "manual_by_topic"


class QosPolicyKind(enum.Enum):
    """Which policy made a writer and a reader incompatible (ROS 2 ``last_policy_kind``)."""

    INVALID = "invalid"
    RELIABILITY = "reliability"
    DURABILITY = "durability"
    DEADLINE = "deadline"
    LIVELINESS = "liveliness"


class QosProfile(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """What a writer offers or a reader requests, plus the timings of the reliable protocol.

    Only reliability, durability, deadline and liveliness take part in matching; history, depth
    and lifespan never prevent a match (ROS 2 rules). The protocol timings are local: a writer and
    a reader with different timings still interoperate.
    """

    reliability: ReliabilityPolicy = ReliabilityPolicy.RELIABLE
    history: HistoryPolicy = HistoryPolicy.KEEP_LAST
    #: samples kept by KEEP_LAST (writer history and reader reorder window)
    depth: int = 10
    #: bound of KEEP_ALL (Fast DDS resource limit default, the "Dmax = 5000" of the ARP paper)
    max_samples: int = 5000
    #: how long a KEEP_ALL ``write`` waits for room before raising ``HistoryFullError``
    max_blocking_time_s: float = 0.1
    durability: DurabilityPolicy = DurabilityPolicy.VOLATILE
    #: longest expected gap between samples; 0 = no deadline
    deadline_s: float = 0.0
    #: longest age from source stamp to delivery; 0 = forever
    lifespan_s: float = 0.0
    liveliness: LivelinessPolicy = LivelinessPolicy.AUTOMATIC
    #: how long a writer may stay silent before it is declared not alive; 0 = forever
    lease_duration_s: float = 0.0
    #: writer heartbeat period (also the proof of life of an unchanged topic)
    heartbeat_period_s: float = 0.1
    #: reader waits this long after seeing a gap before NACKing (tolerates reordering)
    nack_delay_s: float = 0.002
    #: reader repeats an unanswered NACK at this period
    nack_period_s: float = 0.02
    #: longest time a missing sample holds later ones back before it is declared lost
    reorder_timeout_s: float = 0.5
    #: adaptive write batching (as Cyclone DDS's WriteBatch, and as Zenoh batches messages on a
    #: busy link): a writer written faster than ``batch_max_delay_s`` lets up to this many samples
    #: share one Zenoh message, which amortises the per-message cost of Python and Zenoh; a topic
    #: slower than that never waits. 1 = off: every sample is its own message, which a plain
    #: Zenoh subscriber decodes
    batch_max_samples: int = 64
    #: with batching, the longest a written sample waits for its batch to fill; a sample written
    #: after a pause at least this long goes out at once, so a slow topic gains no latency
    batch_max_delay_s: float = 0.0005
    #: a streaming writer lets an acknowledged DATA that asked for an acknowledgement do its
    #: periodic heartbeat (docs/reliability.md "Heartbeats on a streaming topic"). Off by
    #: default for now: with it on, two timing tests (the lost-change staleness bound, the
    #: overload's return within its latency bound) failed under CI's load, not understood yet
    piggyback_heartbeats: bool = False
    #: while a writer is calm (nothing to announce, or, with ``piggyback_heartbeats``, every
    #: reader answered the period's acknowledgement request), its heartbeat period doubles, up
    #: to this multiple of ``heartbeat_period_s``; a NACK or a retune brings it back at once,
    #: an unanswered request holds it (Cyclone DDS's adaptive heartbeat). A streaming
    #: topic costs one ACKNACK from each reader a period (a CEDDP of 200 topics answered 2 000 a
    #: second), a quiet one a wake-up of its driver. What it costs: a lost last sample waits up
    #: to the grown period for its heartbeat. 1 = a fixed period
    heartbeat_backoff: int = 1

    def __post_init__(self) -> None:
        if self.depth < 1:
            raise QosError(f"depth must be >= 1, got {self.depth}")
        if self.max_samples < 1:
            raise QosError(f"max_samples must be >= 1, got {self.max_samples}")
        if self.history is HistoryPolicy.KEEP_LAST and self.depth > self.max_samples:
            raise QosError(
                f"depth {self.depth} exceeds max_samples {self.max_samples}: raise max_samples"
            )
        for name in (
            "max_blocking_time_s",
            "deadline_s",
            "lifespan_s",
            "lease_duration_s",
            "nack_delay_s",
        ):
            value = getattr(self, name)
            if not math.isfinite(value) or value < 0:
                raise QosError(f"{name} must be a finite number of seconds >= 0, got {value}")
        if not 1 <= self.batch_max_samples <= MAX_BATCH:
            raise QosError(
                f"batch_max_samples must be 1 (off) .. {MAX_BATCH}, got {self.batch_max_samples}"
            )
        if not 1 <= self.heartbeat_backoff <= MAX_HEARTBEAT_BACKOFF:
            raise QosError(
                f"heartbeat_backoff must be 1 (off) .. {MAX_HEARTBEAT_BACKOFF}, "
                f"got {self.heartbeat_backoff}"
            )
        for name in (
            "heartbeat_period_s",
            "nack_period_s",
            "reorder_timeout_s",
            "batch_max_delay_s",
        ):
            value = getattr(self, name)
            if not math.isfinite(value) or value <= 0:
                raise QosError(f"{name} must be a finite number of seconds > 0, got {value}")

    @property
    def capacity(self) -> int:
        """How many samples the writer history and the reader window may hold."""
        return self.depth if self.history is HistoryPolicy.KEEP_LAST else self.max_samples

    @property
    def batching(self) -> bool:
        return self.batch_max_samples > 1

    @property
    def reliable(self) -> bool:
        return self.reliability is ReliabilityPolicy.RELIABLE

    @property
    def transient_local(self) -> bool:
        return self.durability is DurabilityPolicy.TRANSIENT_LOCAL


#: ROS 2 ``rmw_qos_profile_default``: KEEP_LAST 10, RELIABLE, VOLATILE.
QOS_DEFAULT: Final = QosProfile()
#: ROS 2 ``rmw_qos_profile_sensor_data``: KEEP_LAST 5, BEST_EFFORT.
QOS_SENSOR_DATA: Final = QosProfile(reliability=ReliabilityPolicy.BEST_EFFORT, depth=5)
#: ROS 2 ``rmw_qos_profile_parameters``: KEEP_LAST 1000, RELIABLE.
QOS_PARAMETERS: Final = QosProfile(depth=1000)
#: Strictly reliable: nothing is lost unless the link is down longer than the reorder timeout.
QOS_RELIABLE_ALL: Final = QosProfile(history=HistoryPolicy.KEEP_ALL)
#: Late joiners get the last sample (ROS 2 "latched" topics, maps, configuration).
QOS_LATCHED: Final = QosProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)

_PRESETS: Final = {
    "default": QOS_DEFAULT,
    "sensor_data": QOS_SENSOR_DATA,
    "parameters": QOS_PARAMETERS,
    "reliable_all": QOS_RELIABLE_ALL,
    "latched": QOS_LATCHED,
}


def qos_from_toml(text: str | bytes) -> QosProfile:
    """Decode a profile from TOML; ``preset = "sensor_data"`` starts from a preset.

    Errors name the offending field, as msgspec reports them.
    """
    raw = msgspec.toml.decode(text)
    if not isinstance(raw, dict):
        raise QosError("a QoS profile must be a TOML table")
    preset = raw.pop("preset", None)
    if preset is not None:
        if preset not in _PRESETS:
            raise QosError(f"unknown preset {preset!r}; choose one of {sorted(_PRESETS)}")
        base = msgspec.to_builtins(_PRESETS[preset])
        raw = {**base, **raw}
    return msgspec.convert(raw, QosProfile)


def load_qos(path: str | Path) -> QosProfile:
    return qos_from_toml(Path(path).read_bytes())


def incompatible_policy(offered: QosProfile, requested: QosProfile) -> QosPolicyKind | None:
    """The first policy for which the reader asks more than the writer offers, or None."""
    if requested.reliable and not offered.reliable:
        return QosPolicyKind.RELIABILITY
    if requested.transient_local and not offered.transient_local:
        return QosPolicyKind.DURABILITY
    if requested.deadline_s > 0 and (
        offered.deadline_s == 0 or offered.deadline_s > requested.deadline_s
    ):
        return QosPolicyKind.DEADLINE
    if (
        requested.liveliness is LivelinessPolicy.MANUAL_BY_TOPIC
        and offered.liveliness is LivelinessPolicy.AUTOMATIC
    ):
        return QosPolicyKind.LIVELINESS
    if requested.lease_duration_s > 0 and (
        offered.lease_duration_s == 0 or offered.lease_duration_s > requested.lease_duration_s
    ):
        return QosPolicyKind.LIVELINESS
    return None


class MatchQos(msgspec.Struct, frozen=True):
    """The part of a profile that travels in a liveliness token key, enough to decide a match."""

    reliable: bool
    transient_local: bool
    manual: bool
    deadline_us: int
    lease_us: int

    def as_profile(self) -> QosProfile:
        return QosProfile(
            reliability=ReliabilityPolicy.RELIABLE
            if self.reliable
            else ReliabilityPolicy.BEST_EFFORT,
            durability=DurabilityPolicy.TRANSIENT_LOCAL
            if self.transient_local
            else DurabilityPolicy.VOLATILE,
            liveliness=LivelinessPolicy.MANUAL_BY_TOPIC
            if self.manual
            else LivelinessPolicy.AUTOMATIC,
            deadline_s=self.deadline_us / 1e6,
            lease_duration_s=self.lease_us / 1e6,
        )


_QOS_CHUNK: Final = re.compile(r"^([RB])([VT])([AM])_(\d{1,15})_(\d{1,15})$")


def encode_match_qos(qos: QosProfile) -> str:
    """One key chunk such as ``RVA_0_0``: reliability, durability, liveliness, deadline and lease
    in integer microseconds (0 = infinite). Integers keep the chunk free of '.' ambiguity and
    make both sides compare exactly the same values."""
    return (
        ("R" if qos.reliable else "B")
        + ("T" if qos.transient_local else "V")
        + ("M" if qos.liveliness is LivelinessPolicy.MANUAL_BY_TOPIC else "A")
        + f"_{round(qos.deadline_s * 1e6)}_{round(qos.lease_duration_s * 1e6)}"
    )


def decode_match_qos(chunk: str) -> MatchQos | None:
    """None for a malformed chunk, so a bad token is counted and ignored, never a crash."""
    found = _QOS_CHUNK.match(chunk)
    if found is None:
        return None
    rel, dur, live, deadline, lease = found.groups()
    return MatchQos(rel == "R", dur == "T", live == "M", int(deadline), int(lease))


def rounded(qos: QosProfile) -> QosProfile:
    """The profile as a peer sees it through the token (durations rounded to microseconds)."""
    decoded = decode_match_qos(encode_match_qos(qos))
    assert decoded is not None
    return decoded.as_profile()
