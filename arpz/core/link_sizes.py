"""What a link carries in one piece: Zenoh's batch size and the channel's fragment size, pure.

Over UDP a Zenoh batch is one datagram, and a datagram larger than one radio frame is cut by IP
and lost whole when one of its frames is (a WiFi frame carries 1500 bytes). Zenoh's default batch
(65 535 bytes) therefore makes 45 frames share one fate, and a message larger than the batch is
cut by Zenoh and lost whole when one piece is. arpz sets the batch to one frame's UDP payload
(``UDP_BATCH_BYTES``) on a session that connects over UDP, and its writers send a sample larger
than one such datagram as fragments (``arpz.core.protocol.wire.DATA_FRAG``) that each fit one, so a
lost frame costs the resend of one fragment. Stream links (TCP, TLS, QUIC, WebSocket, unix
sockets) resend their own segments: Zenoh's default batch stays, and a fragment only has to fit
it (``STREAM_FRAGMENT_BYTES``).

No zenoh import: this is the contracts layer; ``arpz.transport.zenoh`` applies the batch size.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Final, NamedTuple

from arpz.core.endpoints import STREAM_PROTOCOLS, frame_fragment_bytes
from arpz.core.protocol import wire
from arpz.core.protocol.fragments import DEFAULT_FRAGMENT_BYTES, STREAM_FRAGMENT_BYTES

#: one 1500-byte radio frame less the IPv4 (20) and UDP (8) headers
UDP_BATCH_BYTES: Final = 1472
#: Zenoh's own bytes around one message in a UDP batch, beyond its key, attachment and payload
#: (batch and frame headers, the push header, the key's and the extensions' lengths), with a
#: margin. Measured through ``arpz.netem``: a resent fragment of 1280 + 42 attachment bytes on a
#: 58-character key made datagrams of at most 1 4xx bytes (tests/integration/
#: test_large_messages.py checks ``largest_datagram`` <= 1472)
ZENOH_MESSAGE_OVERHEAD: Final = 64
#: the smallest fragment a writer uses, however long its key (a fragment must carry something)
MIN_FRAGMENT_BYTES: Final = 256
_GUID_HEX = "0" * (2 * wire.GUID_BYTES)


class LinkSizes(NamedTuple):
    #: ``transport/link/tx/batch_size`` to set on the session (None: leave Zenoh's default)
    batch_size: int | None
    #: payload bytes of one fragment; a sample larger than this is sent as fragments
    fragment_bytes: int


def link_sizes(endpoints: Sequence[str]) -> LinkSizes:
    """The sizes for a session whose links are ``endpoints`` (its connect endpoints; a router's
    listen endpoints when it connects nowhere). Every endpoint a stream: Zenoh's batch and
    ``STREAM_FRAGMENT_BYTES``. Any UDP endpoint, or none known: one radio frame per datagram
    (``UDP_BATCH_BYTES``) and ``DEFAULT_FRAGMENT_BYTES`` (1280), which with its headers fits it.

    Zenoh takes the smaller of the two ends' batch sizes when a link opens, so a robot that
    connects over UDP gets one-frame datagrams both ways from its own setting; a router that
    also listens on TCP need not shrink its TCP batches (it leaves them to its clients)."""
    fragment_bytes = frame_fragment_bytes(list(endpoints))  # the rule a robot's frames follow
    if fragment_bytes == STREAM_FRAGMENT_BYTES:
        return LinkSizes(None, fragment_bytes)
    return LinkSizes(UDP_BATCH_BYTES, fragment_bytes)


def datagram_fragment_bytes(key: str, datagram_bytes: int = UDP_BATCH_BYTES) -> int:
    """The largest fragment a writer on ``key`` can send so that its resend (on the directed
    key ``{key}/rel/rx/{reader}``, the longest key a fragment goes on, with the 42-byte resend
    header and Zenoh's framing) still fits one ``datagram_bytes`` datagram; at most
    ``DEFAULT_FRAGMENT_BYTES``, at least ``MIN_FRAGMENT_BYTES``."""
    key_bytes = len(wire.directed_key(key, _GUID_HEX).encode())
    room = datagram_bytes - ZENOH_MESSAGE_OVERHEAD - wire.RESEND_FRAG.size - key_bytes
    return max(MIN_FRAGMENT_BYTES, min(DEFAULT_FRAGMENT_BYTES, room))


def writer_fragment_bytes(key: str, link_fragment_bytes: int | None) -> int:
    """A writer's fragment size: its link's (``LinkSizes.fragment_bytes``, None when unknown:
    the UDP one, safe on every link), cut down on a datagram link to what its key leaves room
    for (``datagram_fragment_bytes``)."""
    size = DEFAULT_FRAGMENT_BYTES if link_fragment_bytes is None else link_fragment_bytes
    if size <= DEFAULT_FRAGMENT_BYTES:
        return min(size, datagram_fragment_bytes(key))
    return size


def session_batch_size(connect: Sequence[str], listen: Sequence[str] = ()) -> int | None:
    """``transport/link/tx/batch_size`` for a session (None: leave Zenoh's default). Its
    connect endpoints decide when it has any (``link_sizes``: one radio frame when any is UDP).
    A session that only listens sets it only when every listen endpoint is UDP: Zenoh takes the
    smaller of the two ends' batch sizes when a link opens (checked through ``arpz.netem``: a
    UDP client's 1472 alone kept the router's datagrams to it at 1 361 bytes at most), so a
    router that also listens on TCP leaves its UDP clients to shrink their own links and keeps
    full batches on TCP. Nothing known (scouting only): None."""
    if connect:
        return link_sizes(connect).batch_size
    if listen and not any(e.partition("/")[0] in STREAM_PROTOCOLS for e in listen):
        return UDP_BATCH_BYTES
    return None
