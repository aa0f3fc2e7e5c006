"""Where a robot's sensor samples go: a reliable-channel ``Writer`` or a plain Zenoh publisher.

With ``sensor_qos`` set (the default of the demo and of real deployments), every sensor topic
has an ``arpz.reliability.Writer`` with that QoS: heartbeats, ACKNACK recovery, bounded history,
deadline; a reading the local cache holds back is reported to the channel as "unchanged" so the
topic is not taken for dead. Without it, samples are plain Zenoh puts (no end-to-end recovery;
the CEDDP still counts sequence gaps). A QoS assignment from the CEDDP changes the depth and the
offered deadline of the writer in place (same guid, history and matches).
"""

from __future__ import annotations

import logging

import msgspec

from arpz.reliability import HistoryFullError, QosProfile, Writer, WriterStats
from arpz.transport import Publisher, Transport

log = logging.getLogger(__name__)


class SensorOutput:
    def __init__(self, transport: Transport, key: str, qos: QosProfile | None) -> None:
        self.transport = transport
        self.key = key
        self.qos = qos
        # block=False: a stalled server must never stall the sensing loop; the channel
        # recovers or reports what Zenoh drops under congestion
        self.writer: Writer | None = (
            Writer(transport, key, qos, block=False) if qos is not None else None
        )
        self.publisher: Publisher | None = None if qos is not None else transport.publisher(key)
        #: writes KEEP_ALL refused after max_blocking_time (history full of unacknowledged data)
        self.write_failures = 0

    def send(self, payload: bytes, stamp_ns: int) -> bool:
        """Publish one sample; False (and counted) if a KEEP_ALL history stayed full."""
        if self.writer is None:
            assert self.publisher is not None
            self.publisher.put(payload)
            return True
        try:
            self.writer.write(payload, stamp_ns=stamp_ns)
            return True
        except HistoryFullError as exc:
            self.write_failures += 1
            if self.write_failures in (1, 10, 100) or self.write_failures % 1000 == 0:
                log.error("%s: sample not sent (#%d): %s", self.key, self.write_failures, exc)
            return False

    def unchanged(self) -> None:
        """The local cache held a repeat back: tell the channel the topic is alive and current."""
        if self.writer is not None:
            self.writer.assert_unchanged()

    def retune(self, *, depth: int, deadline_s: float) -> None:
        """Apply a QoS assignment's depth and deadline in place (no-op without the channel)."""
        if self.writer is None or self.qos is None:
            return
        self.qos = msgspec.structs.replace(self.qos, depth=depth, deadline_s=deadline_s)
        self.writer.retune(depth=depth, deadline_s=deadline_s)

    def totals(self) -> dict[str, int]:
        """Channel counters of this topic over every writer it had."""
        totals = _Totals()
        if self.writer is not None:
            totals.add(self.writer.stats())
        return {**totals.__dict__, "write_failures": self.write_failures}

    @property
    def matched(self) -> bool:
        """A reader is listening: a matched reliable reader, or for a plain publisher any Zenoh
        subscriber whose declaration has reached this robot's router (so the first readings are
        not put before the route through a router mesh exists)."""
        if self.writer is not None:
            return self.writer.matched_count > 0
        assert self.publisher is not None
        return self.publisher.matching

    def close(self) -> None:
        if self.writer is not None:
            self.writer.wait_for_acknowledgments(0.5)
            self.writer.close()


class _Totals:
    def __init__(self) -> None:
        self.retransmitted = 0
        self.gapped = 0
        self.overwritten_unacked = 0
        self.deadline_missed = 0

    def add(self, stats: WriterStats) -> None:
        self.retransmitted += stats.retransmitted
        self.gapped += stats.lost
        self.overwritten_unacked += stats.overwritten_unacked
        self.deadline_missed += stats.deadline_missed
