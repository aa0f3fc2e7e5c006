"""Endpoint strings are checked before Zenoh sees them, and resolved without a silent downgrade."""

from __future__ import annotations

import pytest

from arpz.core.config import CeddpConfig, ConfigError, RobotConfig, from_dict
from arpz.core.endpoints import (
    DEFAULT_CONNECT,
    check_endpoints,
    endpoint_address,
    frame_fragment_bytes,
    plain_tcp_beside_tls,
    resolve,
)
from arpz.core.errors import ArpzError
from arpz.core.protocol.fragments import DEFAULT_FRAGMENT_BYTES, STREAM_FRAGMENT_BYTES


@pytest.mark.parametrize(
    "endpoint",
    ["tcp/127.0.0.1:7447", "tls/ceddp.local:7447", "udp/[::1]:7447", "tcp/h:0#iface=eth0",
     "unixsock-stream//tmp/zenoh.sock", "quic/10.0.0.1:7447?x=1"],
)  # fmt: skip
def test_good_endpoints_pass(endpoint: str) -> None:
    check_endpoints([endpoint], field="connect")


@pytest.mark.parametrize(
    ("endpoint", "message"),
    [
        ("tcp/127.0.0.1", "HOST:PORT"),
        ("tcp/127.0.0.1:99999", "0..65535"),
        ("tcp/:7447", "HOST:PORT"),
        ("foo/127.0.0.1:7447", "PROTOCOL one of"),
        ("127.0.0.1:7447", "PROTOCOL/ADDRESS"),
        ("unixsock-stream/", "needs an address"),
    ],
)
def test_bad_endpoints_name_the_field(endpoint: str, message: str) -> None:
    with pytest.raises(ValueError, match=message) as info:
        check_endpoints(["tcp/ok:1", endpoint], field="listen")
    assert "listen[1]" in str(info.value)


def test_configs_refuse_bad_endpoints_with_file_and_field() -> None:
    with pytest.raises(ConfigError, match=r"robot\.toml: .*connect\[0\] 'tcp/x'") as info:
        from_dict({"robot_id": "r1", "connect": ["tcp/x"]}, RobotConfig, source="robot.toml")
    assert isinstance(info.value, ArpzError)
    with pytest.raises(ConfigError, match=r"listen\[0\]"):
        from_dict({"listen": ["tls/0.0.0.0"]}, CeddpConfig, source="ceddp.toml")


def test_resolution_never_replaces_the_json5_endpoints_with_a_default() -> None:
    assert resolve([], ["tls/ceddp:7447"], DEFAULT_CONNECT) == ["tls/ceddp:7447"]
    assert resolve(["tcp/a:1"], ["tls/ceddp:7447"], DEFAULT_CONNECT) == ["tcp/a:1"]
    assert resolve([], [], DEFAULT_CONNECT) == list(DEFAULT_CONNECT)
    assert plain_tcp_beside_tls(["tls/a:1", "tcp/a:2"]) == [1]


@pytest.mark.parametrize(
    ("endpoints", "expected"),
    [
        (["tcp/10.0.0.1:7447"], STREAM_FRAGMENT_BYTES),
        (["tls/server:7447", "quic/server:7448"], STREAM_FRAGMENT_BYTES),
        (["udp/10.0.0.1:7447"], DEFAULT_FRAGMENT_BYTES),
        (["tcp/10.0.0.1:7447", "udp/10.0.0.1:7447"], DEFAULT_FRAGMENT_BYTES),  # may go by UDP
        ([], DEFAULT_FRAGMENT_BYTES),  # not known: the size that is safe on any link
    ],
)
def test_frames_are_cut_for_the_link(endpoints: list[str], expected: int) -> None:
    assert frame_fragment_bytes(endpoints) == expected


@pytest.mark.parametrize(
    ("endpoint", "address"),
    [
        ("tcp/127.0.0.1:7447", ("127.0.0.1", 7447)),
        ("tls/ceddp.local:7447", ("ceddp.local", 7447)),
        ("udp/[::1]:7447#iface=eth0", ("::1", 7447)),
        ("quic/10.0.0.1:7448?rel=1", ("10.0.0.1", 7448)),
        ("unixsock-stream//tmp/zenoh.sock", None),
        ("tcp/nohost", None),
        ("bogus/1.2.3.4:5", None),
    ],
)
def test_endpoint_address_is_the_host_and_port_of_ip_endpoints(
    endpoint: str, address: tuple[str, int] | None
) -> None:
    assert endpoint_address(endpoint) == address
