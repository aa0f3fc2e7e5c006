"""The seam between arpz and a bus: the contract, the real bus and the in-process one.

``arpz.transport.zenoh`` is the only module of arpz that imports zenoh (a Zenoh session);
``arpz.transport.memory`` is an in-process bus with the same contract, for tests. The contract
itself lives with the other contracts (``arpz.core.transport``) so that the channel depends on it
and not on this package; its names are handed on here, where docs/api.md promises them.
"""

from arpz.core.transport import (
    DataCallback,
    Handle,
    HoldingPublisher,
    LivelinessCallback,
    Publisher,
    PullSubscriber,
    QueryHandler,
    Reopenable,
    ReplyCallback,
    SessionSettings,
    Transport,
    TransportError,
    client_link_defaults,
)

__all__ = [
    "DataCallback",
    "Handle",
    "HoldingPublisher",
    "LivelinessCallback",
    "Publisher",
    "PullSubscriber",
    "QueryHandler",
    "Reopenable",
    "ReplyCallback",
    "SessionSettings",
    "Transport",
    "TransportError",
    "client_link_defaults",
]
