"""An in-memory bus that drops, duplicates, delays and reorders, driving the pure machines.

Liveliness tokens travel reliably (as Zenoh's do) but with a delay, so data, tokens and SYNC race
as they do through a router. Time is a ``FakeClock`` advanced in small steps; every machine is
ticked at each step, as the real driver does.
"""

from __future__ import annotations

import heapq
import itertools
import random
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from arpz.core.protocol.actions import Action, Deliver, DeliverRun, Notify, Send, TokenChange
from arpz.core.protocol.events import DataInfo
from arpz.core.protocol.reader_machine import ReaderMachine
from arpz.core.protocol.timers import FakeClock
from arpz.core.protocol.writer_machine import WriterMachine
from arpz.transport.memory import key_matches

Machine = WriterMachine | ReaderMachine


@dataclass
class Link:
    loss: float = 0.0
    duplicate: float = 0.0
    #: base one-way delay and uniform extra delay (the extra makes reordering)
    delay_s: float = 0.001
    jitter_s: float = 0.0


@dataclass
class Node:
    machine: Machine
    delivered: list[tuple[bytes, DataInfo]] = field(default_factory=list)
    events: list[tuple[str, object]] = field(default_factory=list)


class LossyBus:
    def __init__(self, rng: random.Random, link: Link, clock: FakeClock) -> None:
        self.rng, self.link, self.clock = rng, link, clock
        self.nodes: list[Node] = []
        self.tokens: dict[str, int] = {}
        self._queue: list[tuple[float, int, Any]] = []
        self._order = itertools.count()
        self.dropped = 0
        #: nodes whose session is lost (a dead zone): nothing reaches them or leaves them, and
        #: the tokens on each side of the cut vanish for the other, as when Zenoh's lease ends
        self.cut: set[int] = set()
        #: a message for which this returns True is lost (on top of the link's random loss)
        self.drop: Callable[[Send], bool] | None = None

    def add(self, machine: Machine) -> Node:
        node = Node(machine)
        self.nodes.append(node)
        if isinstance(machine, WriterMachine):
            self._token(machine.token_key, True)
        # The watcher sees tokens already present (Zenoh's history=True).
        for key in list(self.tokens):
            if key_matches(machine.watch_expr(), key):
                self._later(0.001, ("token", node, key, True))
        return node

    def remove(self, node: Node) -> None:
        """The process dies: its tokens vanish (the router notices)."""
        self.nodes.remove(node)
        m = node.machine
        mine = [k for k in self.tokens if m.hex in k.split("/")]
        for key in mine:
            self._token(key, False)

    def _owned(self, node: Node) -> list[str]:
        return [k for k in self.tokens if node.machine.hex in k.split("/")]

    def _tell(self, node: Node, key: str, declare: bool) -> None:
        if key_matches(node.machine.watch_expr(), key):
            self._later(0.002, ("token", node, key, declare))

    def partition(self, node: Node) -> None:
        """The node's session is lost: its tokens vanish for everyone else, everyone else's for
        it, and no message crosses until ``heal``. The node's machine lives on (same guid)."""
        self._cross(node, False)
        self.cut.add(id(node))

    def heal(self, node: Node) -> None:
        """The node's session is back: the tokens reappear on both sides."""
        self.cut.discard(id(node))
        self._cross(node, True)

    def _cross(self, node: Node, declare: bool) -> None:
        mine = self._owned(node)
        for other in self.nodes:
            if other is node or id(other) in self.cut:
                continue
            for key in mine:
                self._tell(other, key, declare)
            for key in self._owned(other):
                self._tell(node, key, declare)

    def _later(self, delay_s: float, item: Any) -> None:
        heapq.heappush(self._queue, (self.clock.now_s + delay_s, next(self._order), item))

    def _token(self, key: str, declare: bool) -> None:
        if declare:
            self.tokens[key] = 1
        else:
            self.tokens.pop(key, None)
        for node in self.nodes:
            if id(node) not in self.cut:
                self._tell(node, key, declare)

    def run(self, node: Node, actions: Sequence[Action]) -> None:
        machine = node.machine
        if isinstance(machine, ReaderMachine):
            # after every call into a reader, in every scenario of every test on this bus: the
            # suspects-only ``busy`` says what the scan over all writers says
            assert machine.busy() == machine.busy_scan()
        for action in actions:
            if isinstance(action, Send):
                if id(node) in self.cut:
                    self.dropped += 1
                    continue
                self.send(action)
            elif isinstance(action, Deliver):
                node.delivered.append((action.payload, action.info))
            elif isinstance(action, DeliverRun):
                node.delivered.extend(action.samples())
            elif isinstance(action, Notify):
                node.events.append((action.event, action.status))
            elif isinstance(action, TokenChange):
                if id(node) in self.cut:  # the others learn it at ``heal``
                    if action.declare:
                        self.tokens[action.key] = 1
                    else:
                        self.tokens.pop(action.key, None)
                else:
                    self._token(action.key, action.declare)

    def send(self, msg: Send) -> None:
        if self.drop is not None and self.drop(msg):
            self.dropped += 1
            return
        for node in self.nodes:
            if id(node) in self.cut:
                continue
            for expr, handler in node.machine.subscriptions():
                if not key_matches(expr, msg.key):
                    continue
                copies = 1 + (self.rng.random() < self.link.duplicate)
                for _ in range(copies):
                    if self.rng.random() < self.link.loss:
                        self.dropped += 1
                        continue
                    delay = self.link.delay_s + self.rng.random() * self.link.jitter_s
                    self._later(delay, ("msg", node, handler, msg))

    def step(self, dt_s: float = 0.001) -> None:
        self.clock.advance(dt_s)
        while self._queue and self._queue[0][0] <= self.clock.now_s:
            _, _, item = heapq.heappop(self._queue)
            node = item[1]
            if node not in self.nodes:
                continue
            if item[0] == "msg" and id(node) in self.cut:
                self.dropped += 1  # in flight when the link died
                continue
            if item[0] == "token":
                handler = (
                    node.machine.on_reader_token
                    if isinstance(node.machine, WriterMachine)
                    else node.machine.on_writer_token
                )
                self.run(node, handler(item[2], item[3]))
            else:
                msg: Send = item[3]
                fn = getattr(node.machine, item[2])
                self.run(node, fn(msg.key, msg.payload, msg.attachment))
        for node in list(self.nodes):
            self.run(node, node.machine.tick())

    def run_for(self, duration_s: float, dt_s: float = 0.001) -> None:
        for _ in range(round(duration_s / dt_s)):
            self.step(dt_s)

    def write(self, node: Node, payload: bytes) -> int:
        w = node.machine
        assert isinstance(w, WriterMachine)
        if len(payload) > w.fragment_bytes:  # as the Writer does: DATA_FRAG fragments
            seq, messages, actions = w.write_large(payload)
            self.run(node, actions)
            if id(node) not in self.cut:
                for data, attachment in messages:
                    self.send(Send(w.topic, data, attachment))
            return seq
        seq, ready, actions = w.write(payload)
        self.run(node, actions)
        if ready is not None and id(node) not in self.cut:  # else a later write or tick
            self.send(Send(w.topic, ready[0], ready[1]))
        return seq


def publish(bus: LossyBus, writer: Node, n: int, period_s: float) -> None:
    """Write n samples, waiting (as the blocking write does) while KEEP_ALL has no room."""
    w = writer.machine
    assert isinstance(w, WriterMachine)
    for i in range(n):
        waited = 0
        while not w.has_room():
            bus.step()
            waited += 1
            assert waited < 100_000, "KEEP_ALL writer never got room"
        bus.write(writer, b"%d" % i)
        bus.run_for(period_s)
