"""Small helpers shared by the writer and reader state machines."""

from __future__ import annotations

import logging
import os
from collections import Counter

from arpz.core.protocol import wire
from arpz.core.protocol.qos import MatchQos, decode_match_qos

log = logging.getLogger("arpz.channel")

#: how long a reader keeps the state of a writer whose token vanished (and a writer that of a
#: reader), seconds. A token vanishes when the peer's Zenoh session ends: a dead zone longer
#: than Zenoh's lease, a robot roaming to another address, a CEDDP restart. The peer that comes
#: back within this time is the same incarnation (same guid) and its match goes on where it
#: stopped: nothing it had delivered is delivered again, and what was written in the gap is
#: resent or reported lost. Five minutes is longer than any history a robot holds at the rates
#: of seed 001 (KEEP_ALL's 5 000 samples at 100 Hz last 50 s) and than any outage arpz's lab
#: profiles make; a peer that stays away longer is gone for good and its losses are counted
#: then (docs/reliability.md "Session loss").
AWAY_RETENTION_S = 300.0


def new_guid() -> bytes:
    """A fresh random id per writer/reader object: a restarted process is a new incarnation,
    never confused with the old one, even if it reuses the key."""
    return os.urandom(wire.GUID_BYTES)


class BadInput:
    """Counts malformed or unexpected input by kind; logs the first of each kind as a warning and
    the rest at debug level, so a flood of forged messages cannot flood the log either."""

    def __init__(self, owner: str) -> None:
        self.owner = owner
        self.counts: Counter[str] = Counter()

    def __call__(self, kind: str, detail: object = "", *, race: bool = False) -> None:
        """``race``: expected now and then (a sample overtaking its writer's token at match
        time), so counted but logged at debug level only."""
        self.counts[kind] += 1
        level = logging.WARNING if self.counts[kind] == 1 and not race else logging.DEBUG
        log.log(level, "%s ignored %s (%d so far) %s", self.owner, kind, self.counts[kind], detail)

    def total(self) -> int:
        return sum(self.counts.values())


def parse_token(key: str, role: str, topic: str | None) -> tuple[str, bytes, str, MatchQos] | None:
    """``{topic}/rel/{role}/{guid}/{qos}`` -> (topic, guid, guid hex, qos); None if malformed."""
    split = wire.split_control_key(key, role, 2)
    if split is None:
        return None
    found_topic, (guid_hex, chunk) = split
    if topic is not None and found_topic != topic:
        return None
    try:
        guid = bytes.fromhex(guid_hex)
    except ValueError:
        return None
    qos = decode_match_qos(chunk)
    if len(guid) != wire.GUID_BYTES or qos is None:
        return None
    return found_topic, guid, guid_hex, qos
