"""Zenoh endpoint strings, checked before Zenoh sees them.

Zenoh answers a malformed endpoint (no port, an unknown protocol) only with "Unable to connect"
after the whole connect timeout; checking the syntax up front turns it into a configuration error
that names the field.
"""

from __future__ import annotations

from arpz.core.protocol.fragments import DEFAULT_FRAGMENT_BYTES, STREAM_FRAGMENT_BYTES

#: where a robot connects and the CEDDP listens when neither the TOML nor zenoh_config says
DEFAULT_CONNECT = ("tcp/127.0.0.1:7447",)
DEFAULT_LISTEN = ("tcp/0.0.0.0:7447",)

#: Zenoh link protocols (zenoh 1.x); "proto/host:port" for all but the unix ones
ENDPOINT_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream", "unixpipe", "vsock")
_PATH_PROTOCOLS = ("unixsock-stream", "unixpipe", "vsock")
#: links whose transport resends what it loses (everything but UDP datagrams)
STREAM_PROTOCOLS = ("tcp", "tls", "quic", "ws", "unixsock-stream", "unixpipe", "vsock")


def frame_fragment_bytes(endpoints: list[str]) -> int:
    """The fragment size of a large sample on these links: ``STREAM_FRAGMENT_BYTES`` when every
    endpoint is a stream (its transport resends lost segments, so only Zenoh's 64 KiB batch
    bounds a fragment), else ``DEFAULT_FRAGMENT_BYTES``, one radio frame, so that a lost datagram
    costs one fragment's resend (a UDP link, or none known)."""
    if endpoints and all(e.partition("/")[0] in STREAM_PROTOCOLS for e in endpoints):
        return STREAM_FRAGMENT_BYTES
    return DEFAULT_FRAGMENT_BYTES


def endpoint_address(endpoint: str) -> tuple[str, int] | None:
    """(host, port) of an IP endpoint (``tcp/10.0.0.1:7447``, ``quic/[::1]:7447#...``), the
    host as written (a name or an address, without brackets); None for the other kinds
    (unix sockets, pipes, vsock) and for what does not parse."""
    proto, sep, rest = endpoint.partition("/")
    if not sep or proto not in ENDPOINT_PROTOCOLS or proto in _PATH_PROTOCOLS:
        return None
    address = rest.split("#", 1)[0].split("?", 1)[0]
    host, colon, port = address.rpartition(":")
    if not colon or not host or not port.isdigit():
        return None
    return host.removeprefix("[").removesuffix("]"), int(port)


def check_endpoints(endpoints: list[str], *, field: str) -> None:
    """Raise ValueError naming ``field[i]`` when an endpoint is not ``proto/host:port`` with a
    known protocol and a port 0..65535 (Zenoh itself only says "Unable to connect")."""
    for i, endpoint in enumerate(endpoints):
        where = f"{field}[{i}] {endpoint!r}"
        proto, sep, rest = endpoint.partition("/")
        if not sep or proto not in ENDPOINT_PROTOCOLS:
            raise ValueError(
                f"{where}: an endpoint is PROTOCOL/ADDRESS with PROTOCOL one of "
                f"{', '.join(ENDPOINT_PROTOCOLS)}, e.g. 'tcp/192.168.1.10:7447'"
            )
        address = rest.split("#", 1)[0].split("?", 1)[0]
        if proto in _PATH_PROTOCOLS:
            if not address:
                raise ValueError(f"{where}: {proto} needs an address after the '/'")
            continue
        host, colon, port = address.rpartition(":")
        if not colon or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
            raise ValueError(
                f"{where}: needs HOST:PORT with a port 0..65535, e.g. '{proto}/"
                f"{host or address or '192.168.1.10'}:7447'"
            )


def resolve(
    configured: list[str], from_zenoh_config: list[str], default: tuple[str, ...]
) -> list[str]:
    """The endpoints in force: the TOML's, else the zenoh_config file's, else the default. A
    TOML that says nothing must not replace a JSON5's ``tls/`` endpoints with plain ``tcp/``."""
    return list(configured or from_zenoh_config or default)


def plain_tcp_beside_tls(endpoints: list[str]) -> list[int]:
    """Indexes of plain ``tcp/`` endpoints (refused next to a TLS configuration unless asked)."""
    return [i for i, e in enumerate(endpoints) if e.startswith("tcp/")]
