"""Bundles: a robot's sensor messages of one scheduler tick as one Zenoh message.

Why: at 100 Hz a robot's writers never fill a batch of their own, so eight topics cost eight
Zenoh messages a tick, and on a CEDDP that is also the router each message costs tens of
microseconds of routing and a crossing into Python, whatever its size (benchmarks/RESULTS.md,
issue 17: 71 us of CEDDP CPU a sample). RTPS packs the submessages of several writers bound for
one destination into one message for the same reason; a bundle does it for the messages one
thread put on sibling keys ``P/sensor/{topic}``, in the order they were put.

A bundle travels on ``P/sensor/_bundle``. A topic name cannot start with ``_``, so the key is
never a topic, and a subscriber of ``P/sensor/*`` (the CEDDP's) receives bundles in the same
FIFO as single messages; a subscriber of one topic is widened to its siblings and filters
(``subscription``). Each entry names only its last chunk, so a robot can never put, inside its own
bundle, a message on another robot's key: Zenoh's access control on ``P/**`` still holds.

Layout: the Zenoh attachment is ``!BBH`` (version, kind ``B``, n) and then three arrays in one
``struct``: n name lengths (u8), n attachment lengths (u16, 0: none), n payload lengths (u32);
the payload is, for each entry, its name, its attachment and its payload, concatenated. A decoder
returns None for anything malformed, which the transport passes up unopened so that the reader
counts it as the malformed message it is.
"""

from __future__ import annotations

import functools
import re
import struct
from collections.abc import Callable
from typing import Final

VERSION: Final = 1
KIND: Final = ord("B")
HEADER: Final = struct.Struct("!BBH")
#: the last chunk of a bundle's key (never a topic name: those start with a letter or digit)
CHUNK: Final = "_bundle"
#: the chunk above the keys that are bundled: sensor readings, and nothing else
PARENT_CHUNK: Final = "sensor"
#: entries per bundle at most: bounds the work one (possibly forged) message can cause
MAX_ENTRIES: Final = 256
#: an attachment longer than this is never bundled (its length is a u16)
MAX_ATTACHMENT: Final = 0xFFFF
_NAME = re.compile(r"^[a-z0-9][a-z0-9_\-]*$")

#: (last chunk of the key, payload, attachment or None)
Entry = tuple[str, bytes, bytes | None]


def bundle_key(key: str) -> str | None:
    """The bundle key for messages on ``key``; None when ``key`` is not bundled (not a plain
    ``.../sensor/{topic}`` key)."""
    parent, _, name = key.rpartition("/")
    if not parent.endswith("/" + PARENT_CHUNK) or not _NAME.match(name):
        return None
    return f"{parent}/{CHUNK}"


def is_bundle_key(key: str) -> bool:
    return key.endswith("/" + PARENT_CHUNK + "/" + CHUNK)


def subscription(key_expr: str) -> tuple[str, Callable[[str], bool] | None]:
    """(what to subscribe to, which arriving keys to keep or None for all) so that bundles reach
    a subscriber of ``key_expr``. ``P/sensor/*`` and ``**`` already match the bundle key; one
    topic (``P/sensor/imu``) or a chunk pattern (``P/sensor/i$*``) is widened to ``P/sensor/*``
    and what arrives is filtered by its last chunk (a bundle's key is kept, so that a malformed
    one reaches the reader that counts it). Other keys are not bundled: unchanged."""
    parent, _, last = key_expr.rpartition("/")
    if last in ("*", "**") or not parent.endswith("/" + PARENT_CHUNK):
        return key_expr, None
    if "$*" in last:
        pattern = re.compile(".*".join(re.escape(part) for part in last.split("$*")))

        def keep(key: str) -> bool:
            name = key.rpartition("/")[2]
            return name == CHUNK or pattern.fullmatch(name) is not None

    else:

        def keep(key: str) -> bool:
            name = key.rpartition("/")[2]
            return name in (last, CHUNK)

    return f"{parent}/*", keep


@functools.lru_cache(maxsize=64)
def _table(n: int) -> struct.Struct:
    return struct.Struct(f"!{n}B{n}H{n}I")


def encode(entries: list[Entry]) -> tuple[bytes, bytes]:
    """(payload, attachment) of one bundle; every name must satisfy ``bundle_key``, every
    attachment fit ``MAX_ATTACHMENT``, and 1 <= len(entries) <= MAX_ENTRIES (the caller's)."""
    n = len(entries)
    names = [name.encode() for name, _, _ in entries]
    atts = [att or b"" for _, _, att in entries]
    parts: list[bytes] = []
    for name, (_, payload, _), att in zip(names, entries, atts, strict=True):
        parts += (name, att, payload)
    table = _table(n).pack(*map(len, names), *map(len, atts), *(len(e[1]) for e in entries))
    return b"".join(parts), HEADER.pack(VERSION, KIND, n) + table


def decode(payload: bytes, attachment: bytes | None) -> list[Entry] | None:
    """The entries in order, or None unless every length adds up and every name is a topic."""
    if attachment is None or len(attachment) < HEADER.size:
        return None
    version, kind, n = HEADER.unpack_from(attachment)
    if version != VERSION or kind != KIND or not 1 <= n <= MAX_ENTRIES:
        return None
    table = _table(n)
    if len(attachment) != HEADER.size + table.size:
        return None
    lengths = table.unpack_from(attachment, HEADER.size)
    if sum(lengths) != len(payload):
        return None
    entries: list[Entry] = []
    at = 0
    for i in range(n):
        name_end = at + lengths[i]
        att_end = name_end + lengths[n + i]
        end = att_end + lengths[2 * n + i]
        name = payload[at:name_end].decode("ascii", "replace")
        if not _NAME.match(name):
            return None
        entries.append((name, payload[att_end:end], payload[name_end:att_end] or None))
        at = end
    return entries


def expand(
    key: str, payload: bytes, attachment: bytes | None, keep: Callable[[str], bool] | None = None
) -> list[tuple[str, bytes, bytes | None]]:
    """What a subscriber receives for one Zenoh message: a bundle's entries with their full keys,
    or the message itself (any other key, or a malformed bundle, which the reader then counts);
    only the keys ``keep`` accepts (a widened subscription's filter, see ``subscription``)."""
    if not key.endswith(CHUNK) or not is_bundle_key(key):
        return [(key, payload, attachment)] if keep is None or keep(key) else []
    entries = decode(payload, attachment)
    if entries is None:
        return [(key, payload, attachment)]
    parent = key[: -len(CHUNK)]
    out = [(parent + name, data, att) for name, data, att in entries]
    return out if keep is None else [item for item in out if keep(item[0])]
