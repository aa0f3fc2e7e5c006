from __future__ import annotations

import msgspec
import pytest
from hypothesis import given
from hypothesis import strategies as st

from arpz.core.protocol.qos import (
    QOS_DEFAULT,
    QOS_SENSOR_DATA,
    DurabilityPolicy,
    HistoryPolicy,
    LivelinessPolicy,
    QosPolicyKind,
    QosProfile,
    ReliabilityPolicy,
    decode_match_qos,
    encode_match_qos,
    incompatible_policy,
    qos_from_toml,
    rounded,
)


def test_presets_match_ros2() -> None:
    assert QOS_DEFAULT.depth == 10 and QOS_DEFAULT.reliable and not QOS_DEFAULT.transient_local
    assert QOS_SENSOR_DATA.depth == 5 and not QOS_SENSOR_DATA.reliable


@pytest.mark.parametrize(
    "kwargs",
    [
        {"depth": 0},
        {"max_samples": 0},
        {"deadline_s": -1.0},
        {"heartbeat_period_s": 0.0},
        {"depth": 10, "max_samples": 5},
        {"lifespan_s": float("inf")},
    ],
)
def test_invalid_profiles_are_refused(kwargs: dict[str, object]) -> None:
    with pytest.raises(ValueError):
        QosProfile(**kwargs)  # type: ignore[arg-type]


def test_toml_with_preset_and_a_typo() -> None:
    qos = qos_from_toml('preset = "sensor_data"\ndepth = 7\ndeadline_s = 0.25\n')
    assert qos.depth == 7 and not qos.reliable and qos.deadline_s == 0.25
    assert qos_from_toml('history = "keep_all"').history is HistoryPolicy.KEEP_ALL
    with pytest.raises(msgspec.ValidationError, match="deph"):
        qos_from_toml("deph = 3")
    with pytest.raises(msgspec.ValidationError, match="depth"):
        qos_from_toml("depth = 0")
    with pytest.raises(ValueError, match="unknown preset"):
        qos_from_toml('preset = "nope"')


@pytest.mark.parametrize(
    ("offered", "requested", "policy"),
    [
        (
            QosProfile(reliability=ReliabilityPolicy.BEST_EFFORT),
            QosProfile(),
            QosPolicyKind.RELIABILITY,
        ),
        (QosProfile(), QosProfile(reliability=ReliabilityPolicy.BEST_EFFORT), None),
        (
            QosProfile(),
            QosProfile(durability=DurabilityPolicy.TRANSIENT_LOCAL),
            QosPolicyKind.DURABILITY,
        ),
        (QosProfile(durability=DurabilityPolicy.TRANSIENT_LOCAL), QosProfile(), None),
        (QosProfile(), QosProfile(deadline_s=0.1), QosPolicyKind.DEADLINE),
        (QosProfile(deadline_s=0.2), QosProfile(deadline_s=0.1), QosPolicyKind.DEADLINE),
        (QosProfile(deadline_s=0.1), QosProfile(deadline_s=0.2), None),
        (
            QosProfile(),
            QosProfile(liveliness=LivelinessPolicy.MANUAL_BY_TOPIC),
            QosPolicyKind.LIVELINESS,
        ),
        (
            QosProfile(lease_duration_s=2.0),
            QosProfile(lease_duration_s=1.0),
            QosPolicyKind.LIVELINESS,
        ),
        (QosProfile(depth=1), QosProfile(history=HistoryPolicy.KEEP_ALL, lifespan_s=1.0), None),
    ],
)
def test_compatibility_table(
    offered: QosProfile, requested: QosProfile, policy: QosPolicyKind | None
) -> None:
    assert incompatible_policy(rounded(offered), rounded(requested)) is policy


@given(
    reliable=st.booleans(),
    tl=st.booleans(),
    manual=st.booleans(),
    deadline=st.floats(0, 1e6),
    lease=st.floats(0, 1e6),
)
def test_match_qos_survives_the_token_key(
    reliable: bool, tl: bool, manual: bool, deadline: float, lease: float
) -> None:
    qos = QosProfile(
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if tl else DurabilityPolicy.VOLATILE,
        liveliness=LivelinessPolicy.MANUAL_BY_TOPIC if manual else LivelinessPolicy.AUTOMATIC,
        deadline_s=deadline,
        lease_duration_s=lease,
    )
    chunk = encode_match_qos(qos)
    assert "/" not in chunk and "*" not in chunk
    decoded = decode_match_qos(chunk)
    assert decoded is not None and encode_match_qos(decoded.as_profile()) == chunk


@pytest.mark.parametrize("chunk", ["", "RVA", "XVA_0_0", "RVA_-1_0", "RVA_0_0_0", "RVA_1.5_0"])
def test_malformed_qos_chunks_are_none(chunk: str) -> None:
    assert decode_match_qos(chunk) is None
