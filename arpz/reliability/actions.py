"""What the pure state machines ask their driver to do.

The machines never touch Zenoh, threads or the wall: they return these values and the driver
(``Writer``/``Reader`` over a ``Transport``, or the lossy in-memory bus of the unit tests)
carries them out. One set of machines therefore runs unchanged under tests and in production.
"""

from __future__ import annotations

import msgspec

from arpz.reliability.events import DataInfo


class Send(msgspec.Struct, frozen=True, gc=False):
    key: str
    payload: bytes
    attachment: bytes | None = None


class Deliver(msgspec.Struct, frozen=True, gc=False):
    payload: bytes
    info: DataInfo


class Notify(msgspec.Struct, frozen=True):
    """Fire the event callback named ``event`` (a field of the *EventCallbacks container)."""

    event: str
    status: object


class TokenChange(msgspec.Struct, frozen=True):
    key: str
    declare: bool


Action = Send | Deliver | Notify | TokenChange
