"""What the pure state machines ask their driver to do.

The machines never touch Zenoh, threads or the wall: they return these values and the driver
(``Writer``/``Reader`` over a ``Transport``, or the lossy in-memory bus of the unit tests)
carries them out. One set of machines therefore runs unchanged under tests and in production.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import msgspec

from arpz.core.protocol.events import DataInfo


class Send(msgspec.Struct, frozen=True, gc=False):
    key: str
    payload: bytes
    attachment: bytes | None = None


class Deliver(msgspec.Struct, frozen=True, gc=False):
    payload: bytes
    info: DataInfo


class DeliverRun(msgspec.Struct, frozen=True, gc=False):
    """Deliver ``payloads`` from ``writer`` on ``key``, seqs ``first, first + 1, ...`` stamped
    ``stamps``: a whole in-order run (a batch) as one action, so that a batch of 64 costs one
    allocation and one dispatch, not 64 of each. Each sample still gets its own ``DataInfo``,
    unless the reader takes runs whole (``Reader(on_data_run=...)``)."""

    key: str
    writer: str
    first: int
    stamps: Sequence[int]
    payloads: Sequence[bytes]
    retransmitted: bool = False

    def samples(self) -> Iterator[tuple[bytes, DataInfo]]:
        """Each sample with its own ``DataInfo``; stamps and payloads must pair up exactly."""
        key, writer, retransmitted, first = self.key, self.writer, self.retransmitted, self.first
        for i, (stamp, payload) in enumerate(zip(self.stamps, self.payloads, strict=True)):
            yield payload, DataInfo(key, writer, first + i, stamp, retransmitted)


class Notify(msgspec.Struct, frozen=True):
    """Fire the event callback named ``event`` (a field of the *EventCallbacks container)."""

    event: str
    status: object


class TokenChange(msgspec.Struct, frozen=True):
    key: str
    declare: bool


Action = Send | Deliver | DeliverRun | Notify | TokenChange
