"""What the CEDDP sends a robot: commands, Hello hops and the QoS assignment, on one worker.

``CommandWorker`` owns the downlink: one ``Inlet`` per key (``cmd/{name}`` for each command the
actuator acts on, ``cmd/hello``, ``ceddp/qos``), whose callbacks only queue; one worker thread
decodes and dispatches in arrival order (commands to the actuator, re-arming the command
watchdog; Hello hops and assignments to the agent's handlers), so a slow actuator never blocks
Zenoh's threads. It counts what it received, what it could not decode, and, in plain mode, the
gaps in each key's sequence numbers, and reports the downlink's counters for reconciliation.
"""

from __future__ import annotations

import functools
import logging
import queue
import threading
import time
from collections.abc import Callable

from arpz.channel import MessageLostStatus, QosPolicyKind
from arpz.channel.io import Inlet
from arpz.core import keys
from arpz.core.config import RobotConfig
from arpz.core.messages import (
    COMMAND_DECODER,
    DECODE_ERRORS,
    HELLO_DECODER,
    MESSAGE_COMMAND_DECODER,
    QOS_ASSIGNMENT_DECODER,
    Command,
    Hello,
    InboundCounters,
    QosAssignmentMsg,
)
from arpz.core.msgtypes import MessageTypes
from arpz.core.transport import Transport
from arpz.robot.actuation import Actuator
from arpz.robot.watchdog import CommandWatchdog

log = logging.getLogger(__name__)


class CommandWorker:
    """Thread: one worker (``arpz-commands``) runs the actuator, the watchdog's on_command and
    the two handlers; ``check_watchdog`` runs on the scheduler thread; counters are read by the
    reporting job under ``lock``."""

    def __init__(
        self,
        config: RobotConfig,
        transport: Transport,
        actuator: Actuator,
        watchdog: CommandWatchdog,
        *,
        clock: Callable[[], float],
        on_assignment: Callable[[QosAssignmentMsg], None],
        on_hello: Callable[[Hello], bool],
        on_incompatible: Callable[[str, QosPolicyKind], None],
    ) -> None:
        self.config = config
        self.transport = transport
        self.actuator = actuator
        self.watchdog = watchdog
        self._clock = clock
        self._on_assignment = on_assignment
        self._on_hello = on_hello
        self._on_incompatible = on_incompatible
        self.lock = threading.Lock()
        self.received = 0
        self.decode_errors = 0
        self.inlets: dict[str, Inlet] = {}
        #: plain mode: per downlink key, (writer, next seq expected) and the seqs missed
        self._plain_next: dict[str, tuple[str, int]] = {}
        self._plain_lost: dict[str, int] = {}
        self._queue: queue.SimpleQueue[tuple[str, bytes] | None] = queue.SimpleQueue()
        self._worker = threading.Thread(target=self._loop, name="arpz-commands", daemon=True)
        self._assignment_key = keys.ceddp_qos_key(config.fleet)
        #: the typed commands' types (the actuator's ``command_types``), and their registry
        self._command_types = dict(actuator.command_types)
        self._types: MessageTypes | None = None
        if self._command_types:
            self._types = MessageTypes()
            for msg_type in self._command_types.values():
                self._types.require(msg_type)

    def start(self, command_names: list[str]) -> None:
        """Start the worker and open one Inlet per downlink key."""
        cfg = self.config
        self._worker.start()
        prefix = keys.robot_prefix(cfg.fleet, cfg.robot_id)
        downlink = [(f"{prefix}/cmd/{name}", "command") for name in command_names]
        downlink += [
            (keys.command_key(cfg.fleet, cfg.robot_id, keys.HELLO), "hello"),
            (self._assignment_key, "assignment"),
        ]
        for key, kind in downlink:
            self.inlets[key] = Inlet(
                self.transport,
                key,
                cfg.profile(kind, downlink=True),
                self._enqueue,
                on_incompatible=self._on_incompatible,
                on_lost=functools.partial(self._on_lost, key),
            )

    def wait_for_writers(self, timeout_s: float) -> None:
        """The CEDDP opens its writers towards this robot when it reads the announcement: wait
        (bounded) until they matched, so the first Hello hops and commands find a reader."""
        # commands only: the assignment is TRANSIENT_LOCAL (it comes whenever a CEDDP with QoS
        # control matches) and a fleet may run without one
        readers = [
            i.reader
            for k, i in self.inlets.items()
            if i.reader is not None and k != self._assignment_key
        ]
        deadline = time.monotonic() + timeout_s
        while any(r.matched_count == 0 for r in readers) and time.monotonic() < deadline:
            time.sleep(0.01)
        waiting = [r.key_expr for r in readers if r.matched_count == 0]
        if waiting:
            log.warning(
                "no CEDDP writer matched %d downlink key(s) within %.1f s: %s",
                len(waiting),
                timeout_s,
                ", ".join(waiting[:3]),
            )

    def close(self) -> None:
        """Close the inlets, then let the worker finish what is queued (bounded)."""
        for inlet in self.inlets.values():
            inlet.close()
        self._queue.put(None)
        self._worker.join(timeout=2.0)

    def count_bad(self) -> None:
        with self.lock:
            self.decode_errors += 1

    def check_watchdog(self, now_s: float) -> None:
        """A scheduler job: no command within its deadline (the CEDDP died, the link is down):
        stop safely."""
        with self.lock:
            expired = self.watchdog.check(now_s)
        if not expired:
            return
        log.warning(
            "command watchdog: no %s command within its deadline: safe stop (#%d)",
            ", ".join(expired),
            self.watchdog.total_stops,
        )
        try:
            self.actuator.safe_stop()
        except Exception:  # a failing stop must be loud, but the robot keeps reporting
            log.exception("actuator safe_stop failed")

    def inbound(self) -> dict[str, InboundCounters]:
        """The downlink's counters per CEDDP -> robot key, named by the key's last two chunks
        (``cmd/velocity``, ``cmd/hello``, ``ceddp/qos``)."""
        out: dict[str, InboundCounters] = {}
        for key, inlet in self.inlets.items():
            stats = inlet.stats()
            refused = sum(inlet.refused.values())
            name = "/".join(key.split("/")[-2:])
            if stats is None:
                out[name] = InboundCounters(refused=refused, lost=self._plain_lost.get(key, 0))
                continue
            out[name] = InboundCounters(
                delivered=stats.delivered,
                lost=stats.lost,
                lifespan_expired=stats.lifespan_expired,
                duplicates=stats.duplicates,
                refused=refused,
                matched=stats.matched,
                writers={
                    guid: list(span)
                    for guid, span in (inlet.reader.accounted() if inlet.reader else {}).items()
                },
            )
        return out

    def _enqueue(self, key: str, payload: bytes) -> None:
        self._queue.put((key, payload))

    def _on_lost(self, key: str, status: MessageLostStatus) -> None:
        log.warning("%s: %d message(s) from the CEDDP lost", key, status.total_count_change)

    def _loop(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            key, payload = item
            name = key.rsplit("/", 1)[-1]
            with self.lock:
                self.received += 1
            try:
                if key == self._assignment_key:
                    self._on_assignment(QOS_ASSIGNMENT_DECODER.decode(payload))
                elif name == keys.HELLO:
                    hello = HELLO_DECODER.decode(payload)
                    self._count_plain_gap(key, hello.writer, hello.seq)
                    if not self._on_hello(hello):
                        self.count_bad()
                else:
                    command = self._decode_command(name, payload)
                    self._count_plain_gap(key, command.writer, command.seq)
                    with self.lock:
                        resumed = self.watchdog.on_command(name, self._clock())
                    if resumed:
                        log.info("command watchdog: %s commands again: resuming", name)
                    self.actuator.apply(name, command)
            except DECODE_ERRORS as exc:
                self.count_bad()
                log.warning("undecodable command on %s (%d bytes): %s", key, len(payload), exc)
            except Exception:
                log.exception("actuator failed on a command on %s", key)

    def _decode_command(self, name: str, payload: bytes) -> Command:
        """A value command, or a typed one with its message as ``value``."""
        msg_type = self._command_types.get(name)
        if msg_type is None or self._types is None:
            return COMMAND_DECODER.decode(payload)
        typed = MESSAGE_COMMAND_DECODER.decode(payload)
        message = self._types.decode(msg_type, typed.value)
        return Command(typed.writer, typed.seq, typed.stamp_ns, message)

    def _count_plain_gap(self, key: str, writer: str, seq: int) -> None:
        """Plain mode (no channel on the downlink): count a gap in the payload's seq as lost, as
        the CEDDP does for plain sensor samples (a new writer starts a new count)."""
        inlet = self.inlets.get(key)
        if inlet is None or inlet.reader is not None:
            return
        last_writer, expected = self._plain_next.get(key, (writer, seq))
        if last_writer != writer:
            expected = seq
        if seq > expected:
            self._plain_lost[key] = self._plain_lost.get(key, 0) + seq - expected
        self._plain_next[key] = (writer, max(expected, seq + 1))
