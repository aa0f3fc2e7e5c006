"""The planner interface of the CEDDP, and the Hello relay of seed 001 Fig. 9.

A planner sees only what cache control let through (``on_reading``), Hello probes
(``on_hello``) and fleet changes (``on_robot``); it acts by sending commands through a
``CommandSink``. It runs on the CEDDP's ingest worker thread, never on a Zenoh callback, so it
may take its time, but a slow planner delays ingest (which is measured and reported).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import Protocol

import msgspec

from arpz.core import keys
from arpz.core.messages import Hello, SensorValue, Telemetry
from arpz.core.throttled_log import ThrottledLog

log = logging.getLogger(__name__)
_throttled = ThrottledLog(log)


@dataclass(frozen=True, slots=True)
class Reading:
    robot: str
    topic: str
    value: SensorValue
    stamp_ns: int
    arrival_ns: int
    seq: int


class CommandSink(Protocol):
    def send(self, robot: str, name: str, payload: bytes) -> None:
        """Publish ``payload`` on the robot's ``cmd/{name}`` key."""


class Planner:
    """Base planner: ignores everything. Subclass and override what you need."""

    #: set True to be told of readings cache control discarded (``on_unchanged``): a planner that
    #: judges freshness needs to know an unchanged topic is still alive
    wants_unchanged: bool = False

    def on_unchanged(self, robot: str, topic: str, stamp_ns: int) -> None:
        """A reading equal to the cached one arrived (and was discarded) at source time stamp_ns."""

    def start(self) -> None:
        """Called once when the server starts (start a thread here if the planner needs one)."""

    def stop(self) -> None:
        """Called once when the server stops, before the summary is made."""

    def on_telemetry(self, robot: str, telemetry: Telemetry) -> None:
        """A simulated robot's true pose: only for judging and drawing, never for planning."""

    def on_reading(self, reading: Reading) -> None:
        """A de-duplicated sensor reading."""

    def on_hello(self, robot: str, hello: Hello) -> None:
        """A Hello probe published by ``robot``."""

    def on_robot(self, robot: str, alive: bool) -> None:
        """A robot joined (alive) or left."""

    def tick(self, now_s: float) -> None:
        """Called periodically by the server (metrics period)."""


class CostlyPlanner(Planner):
    """A stand-in for a heavy planning algorithm: every reading costs ``cost_us`` of CPU time
    on the ingest thread (``[overload] planner_cost_us``). It gives a CEDDP a known, small
    capacity, so that overload and its recovery can be rehearsed and tested with few robots."""

    def __init__(self, cost_us: float) -> None:
        self.cost_s = cost_us / 1e6

    def on_reading(self, reading: Reading) -> None:
        until = time.thread_time() + self.cost_s
        while time.thread_time() < until:
            pass


@dataclass
class HelloRelayCounters:
    forwarded_to_relay: int = 0
    returned_to_origin: int = 0
    #: Hellos that could not be forwarded because no relay robot is present
    no_relay: int = 0
    bad_stage: int = 0
    #: Hellos naming an origin that is not a robot id (forged or corrupt): dropped
    bad_origin: int = 0


class HelloRelay(Planner):
    """Origin -> CEDDP -> relay -> CEDDP -> origin, each hop a real publish through the router.

    The relay is the configured robot, or if none is configured, the origin itself (a one-robot
    fleet still measures a full four-hop round trip).
    """

    def __init__(self, sink: CommandSink, writer: str, relay: str | None = None) -> None:
        self.sink = sink
        self.writer = writer
        self.relay = relay
        self.counters = HelloRelayCounters()
        self._present: set[str] = set()
        self._seqs: dict[str, int] = {}
        self._lock = threading.Lock()

    def on_robot(self, robot: str, alive: bool) -> None:
        with self._lock:
            (self._present.add if alive else self._present.discard)(robot)

    def on_hello(self, robot: str, hello: Hello) -> None:
        try:
            keys.check_chunk(hello.origin, what="Hello origin")
        except keys.KeyExprError:
            self.counters.bad_origin += 1
            log.warning("Hello from %s with an invalid origin %r dropped", robot, hello.origin)
            return
        if hello.stage == 0:
            relay = self.relay or hello.origin
            with self._lock:
                known = relay in self._present
            if not known:  # forwarding to an absent robot would lose it silently in Zenoh
                self.counters.no_relay += 1
                _throttled.warning(
                    f"no relay {relay}",
                    "Hello from %s dropped: its relay robot %r is not connected (%d so far); "
                    "set [hello] relay in the CEDDP config to a robot of this fleet",
                    robot,
                    relay,
                    self.counters.no_relay,
                )
                return
            self._forward(relay, hello, stage=1)
            self.counters.forwarded_to_relay += 1
        elif hello.stage == 2:
            self._forward(hello.origin, hello, stage=3)
            self.counters.returned_to_origin += 1
        else:
            self.counters.bad_stage += 1
            log.warning("Hello with stage %d published by %s ignored", hello.stage, robot)

    def _forward(self, robot: str, hello: Hello, *, stage: int) -> None:
        # seq counts per key (docs/protocol.md): one counter per robot's cmd/hello
        seq = self._seqs[robot] = self._seqs.get(robot, 0) + 1
        hop = msgspec.structs.replace(
            hello, writer=self.writer, seq=seq, stamp_ns=time.time_ns(), stage=stage
        )
        self.sink.send(robot, keys.HELLO, msgspec.msgpack.encode(hop))
