"""The bridge's backends and services, without a network: choosing the backend, the clear error
without rclpy, the QoS each backend offers and requests, service type hashes against ROS 2's
own, and the failure response of a failed call."""

from __future__ import annotations

import sys

import msgspec
import pytest

from arpz.bridge import rmw_zenoh as rz
from arpz.bridge.bridge import Bridge, failure_response
from arpz.bridge.factory import INSTALL_HINT, Ros2Unavailable, bridge_class
from arpz.bridge.naming import service_name
from arpz.bridge.type_hash import service_type_hash
from arpz.core.config import ConfigError, Ros2Config, from_dict
from arpz.core.msgtypes import MessageTypes
from arpz.core.protocol.qos import DurabilityPolicy, LivelinessPolicy, QosProfile
from arpz.core.traffic import COMMAND_QOS

#: ROS 2's own service type hashes: rosidl's output in the ROS 2 wheels' ``share/<package>/srv/
#: <Name>.json`` (ros-std-srvs 5.5.1, ros-sensor-msgs 5.5.1, rcl_interfaces 2.3.0)
GOLDEN = {
    "std_srvs/srv/Trigger": (
        "RIHS01_eeff2cd6fa5ad9d27cdf4dec64818317839b62f212a91e6b5304b634b2062c5f"
    ),
    "std_srvs/srv/SetBool": (
        "RIHS01_abe9e4bb6b41b40e6789712c00ec8871923e089af3f667a79992a428cff2da0a"
    ),
    "std_srvs/srv/Empty": (
        "RIHS01_5888399dedec5ccc85ea6451949fd2c9f97bfdf963f9a588821639fcd31b5d19"
    ),
}
#: rcl_interfaces/srv/GetParameters: nested and referenced types (ParameterValue), sequences
GET_PARAMETERS = "string[] names\n---\nParameterValue[] values\n"
GET_PARAMETERS_HASH = "RIHS01_bf9803d5c74cf989a5de3e0c2e99444599a627c7ff75f97b8c05b01003675cbc"


@pytest.mark.parametrize(("service", "expected"), sorted(GOLDEN.items()))
def test_service_type_hashes_are_those_ros2_computes(service: str, expected: str) -> None:
    assert service_type_hash(service, MessageTypes()) == expected


def test_a_service_with_nested_types_hashes_as_ros2_does() -> None:
    types = MessageTypes()
    types.add_service_definition("rcl_interfaces/srv/GetParameters", GET_PARAMETERS)
    assert service_type_hash("rcl_interfaces/srv/GetParameters", types) == GET_PARAMETERS_HASH


def test_services_are_named_under_their_robot() -> None:
    assert service_name("robot1", "dock") == "/robot1/dock"
    assert service_name("east-1", "lamp-on") == "/east_1/lamp_on"


def test_a_failed_call_answers_std_srvs_style_or_not_at_all() -> None:
    types = MessageTypes()
    _, trigger = types.service_types("std_srvs/srv/Trigger")
    response = failure_response(types, trigger, "robot1/dock: gone")
    assert (response.success, response.message) == (False, "arpz bridge: robot1/dock: gone")
    _, set_bool = types.service_types("std_srvs/srv/SetBool")
    assert failure_response(types, set_bool, "x").success is False
    _, empty = types.service_types("std_srvs/srv/Empty")
    assert failure_response(types, empty, "x") is None  # no field to say it in: no response
    _, get_map = types.service_types("nav_msgs/srv/GetMap")
    assert failure_response(types, get_map, "x") is None


def test_the_backend_is_chosen_by_the_config() -> None:
    assert Ros2Config().backend == "rmw_zenoh"
    assert from_dict({"backend": "rclpy"}, Ros2Config, source="t").backend == "rclpy"
    with pytest.raises(ConfigError, match="backend"):
        from_dict({"backend": "dds"}, Ros2Config, source="t")
    assert bridge_class(Ros2Config(enabled=True)) is Bridge
    assert Bridge.backend == "rmw_zenoh"


def test_the_rclpy_backend_without_rclpy_says_how_to_install_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setitem(sys.modules, "arpz.bridge.rclpy_backend", None)  # as if rclpy were absent
    with pytest.raises(Ros2Unavailable, match=r"rclpy") as raised:
        bridge_class(Ros2Config(enabled=True, backend="rclpy"))
    assert INSTALL_HINT in str(raised.value) and isinstance(raised.value, ConfigError)


def test_transient_local_is_offered_only_where_a_history_is_kept() -> None:
    profile = QosProfile(depth=4, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    assert rz.qos_from_profile(profile).durability == rz.VOLATILE  # rmw_zenoh: no cache
    assert rz.qos_from_profile(profile, transient_local=True).durability == rz.TRANSIENT_LOCAL
    assert rz.qos_from_profile(QosProfile(), transient_local=True).durability == rz.VOLATILE


def test_rclpy_profiles_map_every_policy() -> None:
    pytest.importorskip("rclpy", reason="the ros2 extra")
    from rclpy.duration import Duration, Infinite
    from rclpy.qos import DurabilityPolicy as D
    from rclpy.qos import HistoryPolicy as H
    from rclpy.qos import LivelinessPolicy as L
    from rclpy.qos import ReliabilityPolicy as R

    from arpz.bridge.rclpy_backend import command_qos, rclpy_qos

    offered = rclpy_qos(
        rz.qos_from_profile(
            QosProfile(
                depth=7,
                durability=DurabilityPolicy.TRANSIENT_LOCAL,
                deadline_s=0.25,
                lifespan_s=1.5,
                liveliness=LivelinessPolicy.MANUAL_BY_TOPIC,
                lease_duration_s=2.0,
            ),
            transient_local=True,
        )
    )
    assert (offered.reliability, offered.durability, offered.history, offered.depth) == (
        R.RELIABLE,
        D.TRANSIENT_LOCAL,
        H.KEEP_LAST,
        7,
    )
    assert offered.deadline == Duration(nanoseconds=250_000_000)
    assert offered.lifespan == Duration(seconds=1, nanoseconds=500_000_000)
    assert offered.liveliness == L.MANUAL_BY_TOPIC
    assert offered.liveliness_lease_duration == Duration(seconds=2)
    plain = rclpy_qos(rz.qos_from_profile(None))
    assert (plain.reliability, plain.depth, plain.deadline) == (R.BEST_EFFORT, 1, Infinite)
    # a command subscription requests reliability and history only: any publisher's deadline,
    # liveliness and durability satisfy it
    strict = msgspec.structs.replace(COMMAND_QOS, deadline_s=0.5)
    requested = rclpy_qos(command_qos(strict))
    assert (requested.reliability, requested.depth) == (R.RELIABLE, COMMAND_QOS.depth)
    assert requested.durability == D.VOLATILE and requested.deadline == Infinite
    assert requested.liveliness == L.AUTOMATIC
