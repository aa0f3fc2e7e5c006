"""The imports docs/api.md promised before the layers moved into folders still name the same
objects as the new homes, so a team's code written against them keeps running."""

from __future__ import annotations

import importlib

import pytest

MOVED = [
    (
        "arpz.reliability",
        "arpz.channel",
        ["Writer", "Reader", "QosProfile", "QOS_DEFAULT", "load_qos"],
    ),
    ("arpz.zenoh_transport", "arpz.transport.zenoh", ["ZenohTransport"]),
    ("arpz.memory_transport", "arpz.transport.memory", ["MemoryBus", "MemoryTransport"]),
    (
        "arpz.config",
        "arpz.core.config",
        ["RobotConfig", "CeddpConfig", "load_toml", "SensorConfig"],
    ),
    ("arpz.transport", "arpz.core.transport", ["Transport", "SessionSettings", "TransportError"]),
]


@pytest.mark.parametrize(("old", "new", "names"), MOVED, ids=[old for old, _, _ in MOVED])
def test_an_old_import_names_the_same_objects_as_the_new_home(
    old: str, new: str, names: list[str]
) -> None:
    old_module = importlib.import_module(old)
    new_module = importlib.import_module(new)
    for name in names:
        assert getattr(old_module, name) is getattr(new_module, name), f"{old}.{name}"


def test_the_channel_exports_everything_the_old_package_listed() -> None:
    channel = importlib.import_module("arpz.channel")
    reliability = importlib.import_module("arpz.reliability")
    assert sorted(reliability.__all__) == sorted(channel.__all__)
    assert all(getattr(reliability, name) is getattr(channel, name) for name in channel.__all__)
