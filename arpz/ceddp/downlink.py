"""CEDDP -> robot: one reliable-channel writer per robot and command key, and the QoS assignment.

Why one writer per (robot, command) rather than one per command family: a writer's history, its
acknowledgements and its sequence numbers are per key, so a robot that is slow, far or gone
affects only its own writer (KEEP_LAST overwrites and GAPs are its own), and the robot's reader
reconciles exactly against what was written for it. The writers are opened when the robot
announces the commands it acts on, and closed when it has been away for
``arpz.channel.AWAY_RETENTION_S``, so state stays bounded by the robots present. A robot
whose session was lost (a dead zone, a roam) keeps its writers: when it is back, its reader
resumes the match and every command written meanwhile is resent, expired past its lifespan or
GAPed and counted lost by the robot, as the ones before (issue 39: closing the writers at the
leave lost count of about 200 commands a dead zone).

Every command either reaches the robot's reader or is counted: written with no matched reader
(``unmatched``), refused because the robot never announced the command (``refused``), a KEEP_ALL
history full (``write_failures``); the robot reports what it delivered, lost and dropped past the
lifespan, and the summary reconciles the two (arpz/ceddp/summary.py).

Each writer's acknowledgements also say whether the robot is getting its commands now:
``unacknowledged_s(robot, name)`` is how long the oldest command it has not acknowledged has
waited (``CommandAcks``). The hallway mission holds the fleet on it, as on stale readings: a
robot whose commands are lost while its readings still arrive drives on its last command until
its watchdog stops it, and must not be planned around as if it obeyed (issue 39).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Protocol

from arpz.channel import AWAY_RETENTION_S, HistoryPolicy, QosProfile
from arpz.channel.io import Outlet
from arpz.core import keys
from arpz.core.config import TrafficQos
from arpz.core.transport import Transport

log = logging.getLogger(__name__)

#: the Hello hop goes down on ``cmd/hello`` with the Hello profile (one more topic in seed 001)


@dataclass
class DownlinkCounters:
    """One robot's command key, as the CEDDP wrote it."""

    #: messages written (with or without a matched reader)
    written: int = 0
    #: written while no reader of the robot was matched: reached no one
    unmatched: int = 0
    #: refused because the robot does not act on this command (it never announced it)
    refused: int = 0
    write_failures: int = 0
    #: answered by GAP (a reader asked for what KEEP_LAST had overwritten)
    gapped: int = 0
    retransmitted: int = 0
    #: the channel writer's guid and its last seq (what the robot's reader reconciles against)
    guid: str = ""
    last_seq: int = 0

    @property
    def sent_matched(self) -> int:
        """What the robot's reader must account for: delivered + lost + lifespan expired."""
        return self.written - self.unmatched - self.write_failures


class Acknowledging(Protocol):
    """What ``CommandAcks`` reads of a command writer (``arpz.channel.Writer``)."""

    def acknowledged_through(self) -> int: ...

    @property
    def matched_count(self) -> int: ...


class CommandAcks:
    """How far the readers of one command writer acknowledged, dated: the seconds since the
    oldest command no reader has acknowledged was written (0.0: none outstanding).

    From ``Writer.acknowledged_through()``, with two corrections, as that figure also moves
    for reasons other than an acknowledgement. KEEP_LAST makes room by overwriting its oldest
    sample and counts it acknowledged by every reader that had not acknowledged it: with the
    history full of unacknowledged commands (a dead downlink, ``depth`` commands after the
    last acknowledgement) the figure creeps up to ``depth`` behind the last seq at every
    write. So only a figure beyond that (``last - depth``), which an ACKNACK alone can give, counts
    as an acknowledgement. And with no reader matched (a robot away after a lost session, or
    none yet) the figure is the last seq: nobody is acknowledging, and the commands written
    meanwhile stay unacknowledged until a reader acknowledges them. A reader acknowledges
    within the writer's heartbeat period (0.1 s) in normal running.
    """

    def __init__(self, qos: QosProfile) -> None:
        keep_last = qos.history is HistoryPolicy.KEEP_LAST
        #: an advance of ``acknowledged_through`` up to ``last - depth`` may be overwrites
        #: alone (None: KEEP_ALL, which never overwrites)
        self._depth = qos.depth if keep_last else None
        self._lock = threading.Lock()
        #: (seq, monotonic s written) of the last writes, as many as the history holds: the
        #: seqs an acknowledgement that counts can name
        self._written: deque[tuple[int, float]] = deque(
            maxlen=(qos.depth if keep_last else qos.max_samples) + 2
        )
        self._last = 0
        self._acked = 0
        #: when the oldest unacknowledged command was written (None: none outstanding)
        self._since_s: float | None = None

    @property
    def lock(self) -> threading.Lock:
        """Held around a write and its ``written``, so that seqs are counted in write order."""
        return self._lock

    def written(self, now_s: float) -> None:
        """One more sample was written (its seq is the next), at ``now_s`` (monotonic); call
        with ``lock`` held."""
        self._last += 1
        self._written.append((self._last, now_s))
        if self._since_s is None:
            self._since_s = now_s

    def age_s(self, writer: Acknowledging, now_s: float) -> float:
        """Seconds since the oldest command no reader has acknowledged was written, at
        ``now_s`` (monotonic); 0.0 if every one is acknowledged."""
        acked = writer.acknowledged_through()  # before the match: a reader that left between
        matched = writer.matched_count > 0  # the two makes ``acked`` the last seq: not taken
        with self._lock:
            last = self._last
            acknowledged = acked >= last or self._depth is None or acked > last - self._depth
            if matched and acked > self._acked and acknowledged:
                self._acked = acked
                self._since_s = None if acked >= last else self._written_at(acked + 1)
            return 0.0 if self._since_s is None else max(0.0, now_s - self._since_s)

    def _written_at(self, seq: int) -> float:
        first = self._written[0][0]
        return self._written[min(max(seq - first, 0), len(self._written) - 1)][1]


class Downlink:
    """The ``CommandSink`` of the planners: ``send(robot, name, payload)``, thread-safe."""

    def __init__(
        self, transport: Transport, fleet: str, traffic: TrafficQos, *, max_per_robot: int = 64
    ) -> None:
        self._transport = transport
        #: writers one robot may make the CEDDP open (each is a thread and a token): a robot
        #: announcing thousands of command names must not exhaust the CEDDP
        self._max_per_robot = max_per_robot
        #: command names refused per robot because of that bound
        self.over_limit: dict[str, int] = {}
        self._fleet = fleet
        self._traffic = traffic
        #: robots whose presence vanished, with when (monotonic s): their writers wait for them
        self._away_since: dict[str, float] = {}
        self._lock = threading.Lock()
        self._outlets: dict[tuple[str, str], Outlet] = {}
        #: per (robot, command) with a channel writer: its acknowledgements, dated
        self._acks: dict[tuple[str, str], CommandAcks] = {}
        #: per (robot, command); kept after a robot leaves, for the summary
        self.counters: dict[tuple[str, str], DownlinkCounters] = {}

    def open_robot(self, robot: str, commands: list[str]) -> None:
        """The robot acts on ``commands`` (its announcement): open a writer for each new one."""
        self._close_long_away()
        with self._lock:
            self._away_since.pop(robot, None)
        for name in commands:
            try:
                key = keys.command_key(self._fleet, robot, name)
            except keys.KeyExprError:
                log.warning("robot %s announced an invalid command name %r", robot, name)
                continue
            with self._lock:
                if (robot, name) in self._outlets:
                    continue
                if sum(1 for r, _ in self._outlets if r == robot) >= self._max_per_robot:
                    seen = self.over_limit.get(robot, 0)
                    self.over_limit[robot] = seen + 1
                    if not seen:
                        log.warning(
                            "robot %s announced more than %d commands: the rest are refused",
                            robot,
                            self._max_per_robot,
                        )
                    continue
            kind = "hello" if name == keys.HELLO else "command"
            qos = self._traffic.profile(kind, downlink=True)
            outlet = Outlet(self._transport, key, qos, block=False)
            with self._lock:
                if (robot, name) in self._outlets:  # opened meanwhile by another thread
                    stale = outlet
                else:
                    self._outlets[(robot, name)] = outlet
                    self.counters.setdefault((robot, name), DownlinkCounters())
                    if outlet.writer is not None:
                        self._acks[(robot, name)] = CommandAcks(outlet.writer.qos)
                    stale = None
            if stale is not None:
                stale.close(0.0)

    def robot_away(self, robot: str) -> None:
        """The robot's presence vanished: its writers stay open for it to come back to (its
        reader's match resumes), and close after AWAY_RETENTION_S."""
        with self._lock:
            self._away_since.setdefault(robot, time.monotonic())
        self._close_long_away()

    def _close_long_away(self) -> None:
        now = time.monotonic()
        with self._lock:
            gone = [r for r, t in self._away_since.items() if now - t >= AWAY_RETENTION_S]
        for robot in gone:
            self.close_robot(robot)

    def close_robot(self, robot: str) -> None:
        """The robot is gone for good: close its writers (a returning robot announces again)."""
        with self._lock:
            self._away_since.pop(robot, None)
            mine = [k for k in self._outlets if k[0] == robot]
            outlets = [self._outlets.pop(k) for k in mine]
            for k in mine:
                self._acks.pop(k, None)
            for k, outlet in zip(mine, outlets, strict=True):
                self._settle(k, outlet)
        for outlet in outlets:
            outlet.close(0.0)

    def send(self, robot: str, name: str, payload: bytes) -> None:
        with self._lock:
            outlet = self._outlets.get((robot, name))
            counters = self.counters.setdefault((robot, name), DownlinkCounters())
            if outlet is None:
                counters.refused += 1
                if counters.refused in (1, 100) or counters.refused % 10_000 == 0:
                    log.warning(
                        "command %s for robot %s refused (#%d): the robot has not announced it",
                        name,
                        robot,
                        counters.refused,
                    )
                return
            counters.written += 1
            acks = self._acks.get((robot, name))
        before = outlet.unmatched
        if acks is None:
            ok = outlet.send(payload, time.time_ns(), count_unmatched=True)
        else:
            with acks.lock:
                ok = outlet.send(payload, time.time_ns(), count_unmatched=True)
                if ok:
                    acks.written(time.monotonic())
        with self._lock:
            counters.unmatched += outlet.unmatched - before
            if not ok:
                counters.write_failures += 1

    def unacknowledged_s(self, robot: str, name: str) -> float | None:
        """Seconds since the oldest ``name`` command written to ``robot`` that its reader has
        not acknowledged was written (0.0: every one acknowledged; ``CommandAcks``); None when
        that cannot be known: no writer open for it, or plain Zenoh (``reliability = "none"``)."""
        with self._lock:
            outlet = self._outlets.get((robot, name))
            acks = self._acks.get((robot, name))
        if outlet is None or outlet.writer is None or acks is None:
            return None
        return acks.age_s(outlet.writer, time.monotonic())

    def _settle(self, key: tuple[str, str], outlet: Outlet) -> None:
        """Copy the writer's own counters into the summary's (call with the lock held)."""
        c = self.counters[key]
        stats = outlet.stats()
        if stats is None or outlet.writer is None:
            return
        c.gapped, c.retransmitted = stats.lost, stats.retransmitted
        c.guid, c.last_seq = outlet.writer.guid, stats.sent

    def snapshot(self) -> dict[tuple[str, str], DownlinkCounters]:
        self._close_long_away()
        with self._lock:
            for key, outlet in self._outlets.items():
                self._settle(key, outlet)
            return {k: DownlinkCounters(**vars(v)) for k, v in self.counters.items()}

    def close(self) -> None:
        with self._lock:
            items = list(self._outlets.items())
            for key, outlet in items:
                self._settle(key, outlet)
            self._outlets.clear()
        for _, outlet in items:
            outlet.close(0.2)
