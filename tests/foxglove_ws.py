"""A minimal Foxglove WebSocket client for the tests, on the standard library only.

It speaks just what a viewer needs: RFC 6455 framing and, of the Foxglove WebSocket protocol
(subprotocol ``foxglove.sdk.v1``), ``advertise``, ``subscribe`` and binary ``messageData``. So
the tests check the CEDDP's server the way the Foxglove app talks to it, with no dependency. A
minimal protobuf reader decodes the fields of Foxglove's own schemas (``foxglove.LaserScan``)
by the names the advertised schema gives them, without the protobuf package.
"""

from __future__ import annotations

import base64
import contextlib
import hashlib
import json
import os
import socket
import struct
import time
from dataclasses import dataclass
from typing import Any

_GUID = "258EAFA5-E914-47DA-95CA-C5AB0DC85B11"
SUBPROTOCOL = "foxglove.sdk.v1"


@dataclass(frozen=True)
class Message:
    subscription: int
    log_time_ns: int
    payload: bytes


class FoxgloveClient:
    def __init__(self, host: str, port: int, *, timeout_s: float = 5.0) -> None:
        self.sock = socket.create_connection((host, port), timeout=timeout_s)
        self.channels: dict[int, dict[str, Any]] = {}
        self.server_info: dict[str, Any] | None = None
        self._buffer = b""
        self._handshake(host, port)

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self._send_frame(0x8, struct.pack(">H", 1000))
        self.sock.close()

    def __enter__(self) -> FoxgloveClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- WebSocket ----------------------------------------------------------------------------

    def _handshake(self, host: str, port: int) -> None:
        key = base64.b64encode(os.urandom(16)).decode()
        request = (
            f"GET / HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\n"
            f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
            f"Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: {SUBPROTOCOL}\r\n\r\n"
        )
        self.sock.sendall(request.encode())
        while b"\r\n\r\n" not in self._buffer:
            self._fill()
        head, _, self._buffer = self._buffer.partition(b"\r\n\r\n")
        lines = head.decode("latin-1").split("\r\n")
        if " 101 " not in lines[0] + " ":
            raise ConnectionError(f"no WebSocket upgrade: {lines[0]}")
        headers = {
            k.strip().lower(): v.strip() for k, _, v in (x.partition(":") for x in lines[1:])
        }
        accept = base64.b64encode(hashlib.sha1((key + _GUID).encode()).digest()).decode()
        if headers.get("sec-websocket-accept") != accept:
            raise ConnectionError("bad Sec-WebSocket-Accept")

    def _fill(self) -> None:
        chunk = self.sock.recv(65536)
        if not chunk:
            raise ConnectionError("the server closed the connection")
        self._buffer += chunk

    def _take(self, n: int) -> bytes:
        while len(self._buffer) < n:
            self._fill()
        out, self._buffer = self._buffer[:n], self._buffer[n:]
        return out

    def _send_frame(self, opcode: int, payload: bytes) -> None:
        mask = os.urandom(4)
        n = len(payload)
        if n < 126:
            head = struct.pack(">BB", 0x80 | opcode, 0x80 | n)
        elif n < 65536:
            head = struct.pack(">BBH", 0x80 | opcode, 0x80 | 126, n)
        else:
            head = struct.pack(">BBQ", 0x80 | opcode, 0x80 | 127, n)
        masked = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
        self.sock.sendall(head + mask + masked)

    def _recv_frame(self) -> tuple[int, bytes]:
        """One whole message (continuation frames joined); answers pings."""
        data = b""
        opcode = 0
        while True:
            b0, b1 = self._take(2)
            n = b1 & 0x7F
            if n == 126:
                (n,) = struct.unpack(">H", self._take(2))
            elif n == 127:
                (n,) = struct.unpack(">Q", self._take(8))
            mask = self._take(4) if b1 & 0x80 else b""
            payload = self._take(n)
            if mask:
                payload = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
            op = b0 & 0x0F
            if op == 0x9:
                self._send_frame(0xA, payload)
                continue
            if op == 0xA:
                continue
            if op:
                opcode = op
            data += payload
            if b0 & 0x80:
                return opcode, data

    # -- the Foxglove protocol ----------------------------------------------------------------

    def send_json(self, message: dict[str, Any]) -> None:
        self._send_frame(0x1, json.dumps(message).encode())

    def subscribe(self, channel_ids: list[int]) -> dict[int, int]:
        """Subscribe to ``channel_ids``; returns subscription id -> channel id."""
        subs = {i + 1: channel for i, channel in enumerate(channel_ids)}
        self.send_json(
            {
                "op": "subscribe",
                "subscriptions": [{"id": s, "channelId": c} for s, c in subs.items()],
            }
        )
        return subs

    def poll(self, deadline: float) -> Message | None:
        """The next messageData before ``deadline`` (control messages are taken in passing)."""
        while time.monotonic() < deadline:
            self.sock.settimeout(max(deadline - time.monotonic(), 0.01))
            try:
                opcode, data = self._recv_frame()
            except TimeoutError:
                return None
            if opcode == 0x8:
                raise ConnectionError("the server closed the WebSocket")
            if opcode == 0x1:
                self._control(json.loads(data))
            elif opcode == 0x2 and data[:1] == b"\x01":
                sub, log_time = struct.unpack_from("<IQ", data, 1)
                return Message(sub, log_time, data[13:])
        return None

    def _control(self, message: dict[str, Any]) -> None:
        op = message.get("op")
        if op == "serverInfo":
            self.server_info = message
        elif op == "advertise":
            for channel in message["channels"]:
                self.channels[int(channel["id"])] = channel
        elif op == "unadvertise":
            for channel_id in message["channelIds"]:
                self.channels.pop(int(channel_id), None)

    def wait_for_topics(self, topics: set[str], timeout_s: float) -> dict[str, dict[str, Any]]:
        """Read until every topic in ``topics`` is advertised; topic -> channel."""
        deadline = time.monotonic() + timeout_s
        while True:
            by_topic = {c["topic"]: c for c in self.channels.values()}
            if topics <= set(by_topic):
                return by_topic
            if time.monotonic() >= deadline:
                raise AssertionError(
                    f"not advertised within {timeout_s} s: {sorted(topics - set(by_topic))} "
                    f"(advertised: {sorted(by_topic)})"
                )
            self.poll(min(deadline, time.monotonic() + 0.2))


def protobuf_fields(data: bytes) -> dict[int, list[Any]]:
    """Field number -> values of one protobuf message: varints as int, fixed64/fixed32 as raw
    bytes, length-delimited as bytes (a packed repeated field or a nested message)."""
    fields: dict[int, list[Any]] = {}
    i = 0
    while i < len(data):
        key, i = _varint(data, i)
        number, wire = key >> 3, key & 7
        value: Any
        if wire == 0:
            value, i = _varint(data, i)
        elif wire == 1:
            value, i = data[i : i + 8], i + 8
        elif wire == 2:
            n, i = _varint(data, i)
            value, i = data[i : i + n], i + n
        elif wire == 5:
            value, i = data[i : i + 4], i + 4
        else:
            raise ValueError(f"protobuf wire type {wire} not supported")
        fields.setdefault(number, []).append(value)
    return fields


def _varint(data: bytes, i: int) -> tuple[int, int]:
    shift = value = 0
    while True:
        byte = data[i]
        i += 1
        value |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return value, i
        shift += 7


def packed_doubles(raw: bytes) -> list[float]:
    return [v for (v,) in struct.iter_unpack("<d", raw)]


def descriptor_fields(schema_b64: str, message: str) -> dict[str, int]:
    """Field name -> number of ``message`` (e.g. "LaserScan") in an advertised protobuf schema
    (a base64 FileDescriptorSet), so a test reads fields by the names Foxglove documents."""
    descriptor_set = protobuf_fields(base64.b64decode(schema_b64))
    for file in descriptor_set.get(1, []):
        for proto in protobuf_fields(file).get(4, []):
            described = protobuf_fields(proto)
            if described.get(1, [b""])[0].decode() != message:
                continue
            out = {}
            for field in described.get(2, []):
                f = protobuf_fields(field)
                out[f[1][0].decode()] = int(f[3][0])
            return out
    raise KeyError(f"{message} not in the schema")
