"""The CEDDP's event log in the summary is bounded: a robot that rejoins in a loop must not grow
the server's memory, and what falls out is counted."""

from __future__ import annotations

import pytest

from arpz.ceddp import server as server_module
from arpz.ceddp.server import CeddpServer
from arpz.core.config import CeddpConfig
from arpz.transport.memory import MemoryBus, MemoryTransport


def test_the_event_log_keeps_the_newest_and_counts_the_rest(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(server_module, "MAX_EVENTS", 5)
    server = CeddpServer(CeddpConfig(fleet="f", rrd="unused.rrd"), MemoryTransport(MemoryBus()))
    for i in range(12):
        server._event(f"robot r{i} joined")
    summary = server.summary()
    assert [e.split(": ", 1)[1] for e in summary["events"]] == [
        f"robot r{i} joined" for i in range(7, 12)
    ]
    assert summary["events_dropped"] == 7
